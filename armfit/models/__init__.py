"""Arm, device and closed-loop models, the effect library, and the literature models."""

from armfit.models.arm import (
    BASE_PARAMS,
    DEVICE_MASS_KG,
    PARAM_NAMES,
    ClosedLoopModel,
    Param,
    h_arm,
    h_cl,
    h_device,
    z_arm,
)
from armfit.models.effects import EFFECTS, Effect, get_effect
from armfit.models.params import model_from_params, read_params

__all__ = [
    "BASE_PARAMS", "DEVICE_MASS_KG", "PARAM_NAMES", "ClosedLoopModel", "Param", "h_arm",
    "h_cl", "h_device", "z_arm", "EFFECTS", "Effect", "get_effect", "model_from_params",
    "read_params",
]
