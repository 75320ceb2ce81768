"""MaxMI for LeRobot."""
