"""Demonstrations with ground-truth key frames: scripted ManiSkill experts (`lerobot-maxmi-demos`)
and a converter for existing trajectory files (`lerobot-maxmi-convert`)."""
