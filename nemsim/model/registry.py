"""Model registry: every model (NEMSim, its ablations, the baselines) by name.

``build_model(name, scene, rules, config)`` returns an ``nn.Module`` with
``forward(x (B, 2, D, H, W), u (B, 14)) -> x_next``. Baselines register themselves from their own modules
with ``register_model(name, builder, config_cls)``; the registry imports ``nemsim.baselines`` lazily the first
time a name is looked up, so importing this module has no side effects beyond registering NEMSim.

``builder(scene, rules, cfg) -> nn.Module``; ``config_cls`` is a frozen dataclass whose defaults are the
paper configuration. Overrides are a dict (nested dicts or dotted keys for nested dataclasses).
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Callable
from typing import Any

from torch import nn

from nemsim.model.surrogate import NEMSim, NEMSimConfig, apply_overrides

Builder = Callable[[Any, Any, Any], nn.Module]

_REGISTRY: dict[str, tuple[Builder, type, dict[str, Any]]] = {}
_PLUGINS = ("nemsim.baselines",)
_plugins_loaded = False


def register_model(
    name: str, builder: Builder, config_cls: type, defaults: dict[str, Any] | None = None
) -> None:
    """Register ``name``. ``defaults`` are overrides applied to ``config_cls()`` before the caller's."""
    if not dataclasses.is_dataclass(config_cls):
        raise ValueError(f"config_cls for {name!r} must be a dataclass, got {config_cls!r}")
    _REGISTRY[name] = (builder, config_cls, dict(defaults or {}))


def _load_plugins() -> None:
    global _plugins_loaded
    if _plugins_loaded:
        return
    _plugins_loaded = True
    for module in _PLUGINS:
        try:
            importlib.import_module(module)
        except ModuleNotFoundError as err:  # the baselines package may not exist yet
            if err.name != module:
                raise


def available_models() -> list[str]:
    _load_plugins()
    return sorted(_REGISTRY)


def _entry(name: str) -> tuple[Builder, type, dict[str, Any]]:
    if name not in _REGISTRY:
        _load_plugins()
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
    return NEMSim(rules, cfg)


register_model("nemsim", _build_nemsim, NEMSimConfig)
register_model("nemsim-no-eic", _build_nemsim, NEMSimConfig, {"use_eic": False})
register_model("nemsim-no-mac", _build_nemsim, NEMSimConfig, {"use_mac": False})
register_model("nemsim-no-mrc", _build_nemsim, NEMSimConfig, {"use_mrc": False})
