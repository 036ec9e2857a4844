"""The VLA model zoo: two-stage modules with the published dimensions of each architecture."""

from shared.models.base import Handoff, ModelIO, VLAModel
from shared.models.registry import architectures, build_model, get_architecture, register

__all__ = ["Handoff", "ModelIO", "VLAModel", "architectures", "build_model", "get_architecture", "register"]
