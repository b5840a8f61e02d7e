"""Detector training and its data: the synthetic village set, the small YOLOv8n-layout graph."""
