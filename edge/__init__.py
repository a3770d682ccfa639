"""Edge runtime: frame sources, ONNX SCR inference, PnP pose, timings. Imports neither torch nor onnx."""
