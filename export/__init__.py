"""Export of a trained model: ONNX float reference and the fixed-point blob and C source."""
