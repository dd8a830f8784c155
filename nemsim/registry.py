"""Model registry: every model (NEMSim, its ablations, the baselines) by name.

``build_model(name, scene, rules, config)`` returns an ``nn.Module`` with
``forward(x (B, 2, D, H, W), u (B, 14)) -> x_next``. The registry sits above ``nemsim.model`` and
``nemsim.baselines`` and registers both here, so neither package imports it (package dependencies point one
way: baselines -> model -> rules; registry -> both). Other models (tests, experiments) register with
``register_model(name, builder, config_cls)``.

``builder(scene, rules, cfg) -> nn.Module``; ``config_cls`` is a frozen dataclass whose defaults are the
paper configuration. Overrides are a dict (nested dicts or dotted keys for nested dataclasses).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

from torch import nn

from nemsim.baselines import cno, convlstm, deeponet, fno, uno
from nemsim.model.surrogate import NEMSim, NEMSimConfig, apply_overrides

Builder = Callable[[Any, Any, Any], nn.Module]

_REGISTRY: dict[str, tuple[Builder, type, dict[str, Any]]] = {}


def register_model(
    name: str, builder: Builder, config_cls: type, defaults: dict[str, Any] | None = None
) -> None:
    """Register ``name``. ``defaults`` are overrides applied to ``config_cls()`` before the caller's."""
    if not dataclasses.is_dataclass(config_cls):
        raise ValueError(f"config_cls for {name!r} must be a dataclass, got {config_cls!r}")
    _REGISTRY[name] = (builder, config_cls, dict(defaults or {}))


def available_models() -> list[str]:
    return sorted(_REGISTRY)


def _entry(name: str) -> tuple[Builder, type, dict[str, Any]]:
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown model {name!r}; expected one of {available_models()}") from None


def model_config(name: str, scene=None, overrides: dict[str, Any] | None = None):
    """The config dataclass of ``name`` with its registered defaults and ``overrides`` applied."""
    _, config_cls, defaults = _entry(name)
    cfg = config_cls()
    if defaults:
        cfg = apply_overrides(cfg, defaults)
    if overrides:
        cfg = apply_overrides(cfg, overrides)
    return cfg


def build_model(name: str, scene, rules, config: dict[str, Any] | None = None) -> nn.Module:
    """Build model ``name`` for ``scene`` with the compiled ``rules`` (RuleTensors) and config overrides."""
    builder, config_cls, _ = _entry(name)
    if dataclasses.is_dataclass(config) and not isinstance(config, type):
        cfg = config
    else:
        cfg = model_config(name, scene, config)
    return builder(scene, rules, cfg)


def _build_nemsim(scene, rules, cfg: NEMSimConfig) -> nn.Module:
    if cfg.domain in ("quarter", "section"):  # the mirror halo needs the full field's lateral size
        if cfg.domain == "quarter" and (scene is None or getattr(scene, "symmetry", "none") != "d4"):
            raise ValueError(f"a quarter-domain model needs a scene with the square's symmetry, got "
                             f"{getattr(scene, 'name', scene)!r}")
        if scene is None or scene.field_shape[-1] != scene.field_shape[-2]:
            raise ValueError(f"a section-domain model needs a square grid (the trench's field is unfolded "
                             f"to it), got {getattr(scene, 'name', scene)!r}")
        size = int(scene.field_shape[-1])
        if cfg.full_size not in (0, size):
            raise ValueError(f"the model was built for a field of {cfg.full_size} voxels, the scene "
                             f"{scene.name!r} has {size}")
        cfg = dataclasses.replace(cfg, full_size=size)
    return NEMSim(rules, cfg)


register_model("nemsim", _build_nemsim, NEMSimConfig)
register_model("nemsim-no-eic", _build_nemsim, NEMSimConfig, {"use_eic": False})
register_model("nemsim-no-mac", _build_nemsim, NEMSimConfig, {"use_mac": False})
register_model("nemsim-no-mrc", _build_nemsim, NEMSimConfig, {"use_mrc": False})
register_model("convlstm", lambda scene, rules, cfg: convlstm.ConvLSTM3d(cfg), convlstm.ConvLSTMConfig)
register_model("fno", lambda scene, rules, cfg: fno.FNO3d(cfg), fno.FNOConfig)
register_model("uno", lambda scene, rules, cfg: uno.UNO3d(cfg), uno.UNOConfig)
register_model("cno", lambda scene, rules, cfg: cno.CNO3d(cfg, rules), cno.CNOConfig)
register_model("deeponet", lambda scene, rules, cfg: deeponet.DeepONet3d(cfg, rules), deeponet.DeepONetConfig)
register_model("cno-prior", lambda scene, rules, cfg: cno.CNO3d(cfg, rules), cno.CNOConfig,
               {"rulefeat": True})
register_model("deeponet-prior", lambda scene, rules, cfg: deeponet.DeepONet3d(cfg, rules),
               deeponet.DeepONetConfig, {"rulefeat": True})
