"""Export: SCR network (and later the Gaussian models) to ONNX bundles. Desktop side, needs torch and onnx."""
