"""Contract of the object detector (requirements DET-1 - DET-3): keys in/out and parameters.

Boxes are in the input image's pixels (continuous convention: the image spans [0, W] x [0, H]),
the same form the simulator's sim/truth/boxes uses, so the two compare directly.
"""
from aeroperception.schemas import Detection2DArray, DiagnosticStatus, Image
from aeroperception.services.runtime import Param, Topic, Topics

from .yolo import PROVIDERS

NAME = "detector"
INPUTS = Topics(
    Topic("sensors/camera/left/image", Image, note="newest frame wins"),
)
OUTPUTS = Topics(
    Topic("perception/detections", Detection2DArray, 10.0,
          note="at most inference_frequency_hz; stamped with the image's stamp"),
    Topic("perception/detector_health", DiagnosticStatus, 1.0,
          note="OK / WARN (slow, no images) / ERROR (no model)"),
)
# The bundled model, relative to this package (tools/training/train_detector.py makes it; models/MODEL_CARD.md).
BUNDLED_MODEL = "models/aero_sim_det.onnx"
PARAMS = [
    Param("model_path", BUNDLED_MODEL,
          description="YOLOv8 / YOLO11 / YOLO26 (end-to-end) ONNX export (relative: working directory, else the detector package); live"),
    Param("classes_file", "",
          description="class names, one a line; used when the model has no 'names' metadata (80 classes: COCO)"),
    Param("confidence_threshold", 0.40, "", 0.0, 1.0, description="best class score must exceed this"),
    Param("nms_threshold", 0.45, "", 0.0, 1.0, description="same-class boxes overlapping more (IoU) are suppressed"),
    Param("inference_frequency_hz", 10.0, "Hz", 0.1, 60.0, description="at most this many frames per second"),
    Param("intra_op_threads", 1, "", 1, 16, description="onnxruntime threads for one inference"),
    Param("execution_provider", "cpu", choices=tuple(PROVIDERS),
          description="ONNX Runtime execution provider; one this onnxruntime lacks is refused, naming what it has"),
    Param("input_width", 0, "px", 0, 4096, description="model input width; 0: the model's (dynamic: 640)"),
    Param("input_height", 0, "px", 0, 4096, description="model input height; 0: the model's (dynamic: 640)"),
    Param("max_detections", 300, "", 1, 1000, description="per image, best first"),
    Param("image_timeout_s", 2.0, "s", 0.2, 60.0, description="no image for this long -> health WARN"),
]
