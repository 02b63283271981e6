"""Multiple-model mixers: the IMM (p003) and the EKF/UKF blend (p004)."""

from .blend import Blend, switching_statistics
from .imm import IMM, SubspaceEmbedding, combine_gaussians

__all__ = ["IMM", "Blend", "SubspaceEmbedding", "combine_gaussians", "switching_statistics"]
