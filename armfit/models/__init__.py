"""Arm, device and closed-loop models, the effect library, and the literature models."""

from armfit._lazy import lazy_exports

#: The package's names and the module each comes from, imported on first use (so
#: that importing one light module of the package does not load the others).
_EXPORTS: dict[str, str] = {
    "BASE_PARAMS": "armfit.models.arm",
    "DEVICE_MASS_KG": "armfit.models.arm",
    "PARAM_NAMES": "armfit.models.arm",
    "ClosedLoopModel": "armfit.models.arm",
    "Param": "armfit.models.arm",
    "h_arm": "armfit.models.arm",
    "h_cl": "armfit.models.arm",
    "h_device": "armfit.models.arm",
    "z_arm": "armfit.models.arm",
    "EFFECTS": "armfit.models.effects",
    "Effect": "armfit.models.effects",
    "get_effect": "armfit.models.effects",
    "model_from_params": "armfit.models.params",
    "read_params": "armfit.models.params",
}


__all__ = [
    "BASE_PARAMS", "DEVICE_MASS_KG", "PARAM_NAMES", "ClosedLoopModel", "Param", "h_arm",
    "h_cl", "h_device", "z_arm", "EFFECTS", "Effect", "get_effect", "model_from_params",
    "read_params",
]


__getattr__, __dir__ = lazy_exports(globals(), _EXPORTS)
