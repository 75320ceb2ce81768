"""Key-state discovery: KSL-Net, the MaxMI criterion, diversity terms and NMS."""
