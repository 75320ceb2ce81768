"""CoTPC policies (`cotpc`, `cotpc_maxmi`).

Importing the package only registers the config types, which keeps plugin discovery cheap; LeRobot
loads `modeling_cotpc` and `processor_cotpc` by naming convention when a policy is built.
"""

from .configuration_cotpc import CotpcConfig, CotpcMaxmiConfig

__all__ = ["CotpcConfig", "CotpcMaxmiConfig"]
