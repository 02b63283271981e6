"""Multiple-model mixers: the IMM (p003) and the EKF/UKF blend (p004)."""

from .blend import Blend
from .imm import IMM, SubspaceEmbedding, combine_gaussians

__all__ = ["IMM", "Blend", "SubspaceEmbedding", "combine_gaussians"]
