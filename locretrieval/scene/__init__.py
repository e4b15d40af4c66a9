"""Scenes: database and query images with cameras, poses and tags."""

from locretrieval.scene.types import CAMERA_MODELS, Camera, ImageSet, Scene

__all__ = ["CAMERA_MODELS", "Camera", "ImageSet", "Scene"]
