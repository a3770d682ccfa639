"""Firmware bridge: poses to a microcontroller or flight controller over serial. Imports neither torch nor onnx."""
