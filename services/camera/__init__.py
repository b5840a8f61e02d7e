"""camera: a real camera's frames into sensors/camera/{left,right}/image and their camera models
into .../info (issue 34, item 2): a V4L2/UVC device, a GStreamer pipeline, a video file or a folder
of images through OpenCV's capture; mono, two devices, or one side-by-side frame; calibration from
OpenCV, Kalibr or ROS files. Stalled devices are re-opened, drops counted, never a crash.
"""
