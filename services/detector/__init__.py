"""Object detector: any YOLOv8-format ONNX on the left camera -> perception/detections (requirements DET-1 - DET-3)."""
