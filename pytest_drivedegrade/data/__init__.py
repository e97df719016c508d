"""Data: the frame model, the nuScenes-format reader and the embedded rendered world."""
