"""Exports for the engine bundle (ONNX graphs, parity vectors)."""

from .step_graph import OnnxStepRunner, export_step_onnx, io_spec

__all__ = ["OnnxStepRunner", "export_step_onnx", "io_spec"]
