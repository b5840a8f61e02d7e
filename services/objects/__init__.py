"""Objects: per-image detections -> tracked objects in the world (ENU + lat/lon about home)."""
