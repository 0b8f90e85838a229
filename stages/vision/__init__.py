"""Calibration, segmentation and video input (OpenCV, pycolmap)."""
