"""Object detector: any YOLOv8-format ONNX on the left camera -> perception/detections (seed 000 §4.2)."""
