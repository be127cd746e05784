"""The TacTip scene simulator and hardware stand-ins.

It lives beside the Pi runtime (not in ``host``) so that the runtime can take
``--camera sim://walk`` without importing the host toolkit; it needs only numpy
and OpenCV. The host commands (``host simulate``, ``host view``, ...) wrap it.
"""
from device.config import ConfigError
from device.profile import SensorProfile, builtin_profiles, load_profile
from .scene import (EFFECTS, PRESETS, SURFACE_LABELS, TEXTURE_LABELS, Effect, Scene,
                    builtin_scenes, load_scene, parse_scene)
from .simulator import TRUTH_KEYS, Simulator

__all__ = ["ConfigError", "SensorProfile", "builtin_profiles", "load_profile", "EFFECTS",
           "PRESETS", "SURFACE_LABELS", "TEXTURE_LABELS", "Effect", "Scene", "builtin_scenes",
           "load_scene", "parse_scene", "TRUTH_KEYS", "Simulator"]
