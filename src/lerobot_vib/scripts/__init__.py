"""Console entry points, in LeRobot's CLI style (draccus `--key=value`)."""
