"""torch → ONNX export of trained policies, with their contract in metadata and a parity check."""
