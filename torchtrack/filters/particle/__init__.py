"""The bootstrap particle filter, its resampling schemes, and the multiple-model particle filter for joint
tracking and classification."""

from torchtrack.filters.particle import resampling
from torchtrack.filters.particle.filter import ParticleFilter, ParticleRunResult, ParticleState, ParticleUpdateInfo
from torchtrack.filters.particle.jtc import MMPFOutput, MMPFState, MultipleModelParticleFilter, paper_bank

__all__ = [
    "MMPFOutput", "MMPFState", "MultipleModelParticleFilter", "ParticleFilter", "ParticleRunResult",
    "ParticleState", "ParticleUpdateInfo", "paper_bank", "resampling",
]
