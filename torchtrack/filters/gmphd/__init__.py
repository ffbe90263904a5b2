"""The labelled Gaussian-mixture PHD filter and the enhanced GM-PHD tracker of Aguilar, Ortner & Zerubia (2023):
the recursion, label management, adaptive birth, the Bernoulli existence and grey level per label."""

from torchtrack.filters.gmphd.filter import GMPHD, MixtureState
from torchtrack.filters.gmphd.input_aware import InputAwareGMPHD
from torchtrack.filters.gmphd.presets import enhanced_gmphd, labelled_gmphd
from torchtrack.filters.gmphd.tracker import GMPHDTracker

__all__ = ["GMPHD", "GMPHDTracker", "InputAwareGMPHD", "MixtureState", "enhanced_gmphd", "labelled_gmphd"]
