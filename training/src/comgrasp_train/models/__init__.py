"""Component VQ-VAE tokenizers (and, later, the coordinated Transformers)."""

from .configs import PRESETS, ComponentConfig, LossConfig, ModelConfig, TrainConfig, VQConfig, make_config
from .quantizer import EMAResetQuantizer
from .streaming import DecoderStep, StreamingDecoder
from .vq_losses import compute_loss, make_optimizer, make_scheduler, vq_training_step
from .vqvae import ComponentVQ, ComponentVQVAE, build_vq, count_parameters, fit_to_tokens

__all__ = [
    "PRESETS", "ComponentConfig", "LossConfig", "ModelConfig", "TrainConfig", "VQConfig", "make_config",
    "EMAResetQuantizer", "DecoderStep", "StreamingDecoder", "compute_loss", "make_optimizer",
    "make_scheduler", "vq_training_step", "ComponentVQ", "ComponentVQVAE", "build_vq",
    "count_parameters", "fit_to_tokens",
]
