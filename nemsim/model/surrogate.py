"""NEMSim: the composed surrogate F_θ(x_t, u_t; R, M) (eq:learned_transition).

  (z, b, z̄) = SE(x)                                eq:se                 (encoder.py)
  λ = EIC(z̄, u; R)                                  eq:base_rate, eq:primary_intensity   (eic.py)
  α = MAC(λ, z̄, u; R),  T = λ ⊙ α                   eq:rule_based_routing, eq:mechanism_attribution,
                                                    eq:emc_overview       (mac.py)
  Δz, (S, P, G, w) = MRC(z, z̄, u, T)                eq:event_basis_signature ... eq:latent_update (mrc.py)
  z̃ = z + Δz,  x̂ = x + Dec(z̃, b, x)                 eq:decoder            (decoder.py)

Paper configuration ([supp_training]): stem 12, widths (12, 18, 24), 18 latent channels, M = 3 families,
R_b = 4 modes, readout width 24. Ablations are switches, not forks: ``use_eic``, ``use_mac``, ``use_mrc``;
perturbed rule libraries (``nemsim.rules.perturb``) are simply passed in as ``rules``.

Where the paper is silent: the state is edge-padded to a multiple of 4 per axis and the prediction cropped
back (every scene's odd size works); z lives at 1/4 resolution, no convolution runs at full resolution; the
rule side runs in fp32 under bf16 autocast. ``clamp_input`` / ``clamp_output`` clamp the network's input
and the next state to [-1, 1], the range of every valid (SDF/d_max clipped) state, so a drifted voxel is
neither amplified nor accumulated over a long rollout. Further options, each explained in its module:
``monotone_eps`` (``monotone``), ``control_saturation`` (``saturation``), ``transport_input``
(``transport``), ``angle_features``, ``flux_gate`` (``gate``); an older checkpoint loads the default.

Fast path: ``precompute(u)`` evaluates once what depends only on the controls and the fixed rules (rule
kinetics, EIC's control modulation, α^anc, S, A, K, the MRC head products) and ``step(x, cache)`` does the
rest; ``forward(x, u)`` is ``step(x, precompute(u, fused=False))``, so a constant-control rollout pays for
the rule side once.

Quarter domain (``domain = "quarter"``, not in the paper; "model only what a scene needs"): on a scene with
the square's symmetry (``nemsim.symmetry``) the network runs on the lower quadrant of the field, whose high
lateral faces lie on the hole axis; ``_pad`` gives them the mirror halo of the full field, so a convolution
near the axis sees what it would see on the whole field. The GroupNorm statistics and the context pooling
are the quadrant's own: a convolution with an unsymmetric kernel does not commute with the mirrors, so a
network trained on the full field needs retraining on the quadrant. The predicted quadrant is averaged with
its transpose (the diagonal mirror), so a prediction has all 8 symmetries exactly. Rollouts run on the
quadrant (``nemsim.evaluation.rollout`` folds x_0 and unfolds the trajectory); ``predict`` also accepts a
full field.

Cross-section (``domain = "section"``, a trench; ``nemsim.symmetry.FieldFold``): the same network on 2 equal
rows of y and the low half of x, the trench axis on the high W face with its mirror halo. Its 3x3x3
convolutions run in line mode (``nemsim.model.layers``): y is periodic and every feature constant along it,
so each kernel acts as its sum over y, the stem takes the two rows to one and every later grid has one row.
The decoder's voxel shuffle gives the two rows back (its two y sub-voxels), and they are averaged, so every
state is exactly constant along the line. The state dict is the 3-D network's.

Multi-step prediction (``steps_per_call`` = k, not in the paper; k = 1 is the paper's model): one call
predicts x̂_{t+j} = clamp(x_t + r_j, -1, 1), j = 1..k, with cumulative residuals r_j from the decoder's
extra-step head, so a rollout makes ~1/k of the network calls. ``predict(x, cache)`` returns the k states
(B, k, 2, D, H, W); ``step`` the first of them.
"""

from __future__ import annotations

import dataclasses
from dataclasses import asdict, dataclass, field
from typing import Any, Literal

import torch
import torch.nn.functional as F
from torch import nn

from nemsim.controls import N_CONTROLS
from nemsim.model.angle_features import N_ANGLE_FEATURES, angle_features
from nemsim.model.decoder import DecoderConfig, ResidualDecoder
from nemsim.model.eic import EICConfig, EventIntensityCompiler, UnstructuredIntensity
from nemsim.model.encoder import EncoderConfig, StateEncoder
from nemsim.model.gate import ion_flux_gate
from nemsim.model.layers import Conv3d
from nemsim.model.mac import MACConfig, MechanismAttributionCompiler
from nemsim.model.monotone import MONOTONE_AXIS_EPS, MONOTONE_EPS
from nemsim.model.mrc import MechanismResponseCompiler, MRCConfig
from nemsim.model.rule_buffers import RuleBuffers
from nemsim.model.saturation import CONTROL_SATURATION, check_saturation, saturate_controls
from nemsim.model.transport import TransportConfig, species_weights, transport_field
from nemsim.model.unpack import NO_FINISH, Finish, write_states
from nemsim.model.window import WindowRun, splice_latent
from nemsim.symmetry import FieldFold, model_fold


@dataclass(frozen=True)
class NEMSimConfig:
    stem: int = 12  # encoder stem width
    widths: tuple[int, int, int] = (12, 18, 24)  # encoder pyramid widths
    latent_channels: int = 18  # channels of z
    context_dim: int = 24  # size of the compact state context z̄
    n_families: int = 3  # M
    n_modes: int = 4  # R_b
    readout_width: int = 24  # MRC trunk width
    decoder_widths: tuple[int, int] = (24, 16)  # decoder widths at 1/4 and 1/2 resolution
    decoder_out_scale: float = 0.1  # init scale of the decoder's last convolution
    decoder_refine: int = 0  # residual blocks at 1/2 resolution in the decoder (0 = the paper-size decoder)
    use_eic: bool = True  # False: w/o EIC ablation
    use_mac: bool = True  # False: w/o MAC ablation
    use_mrc: bool = True  # False: w/o MRC ablation
    clamp_input: bool = True  # the network sees clamp(x, -1, 1) (identity on valid states; see forward)
    clamp_output: bool = True  # next state projected onto [-1, 1], the range of any valid state (docstring)
    kinetics: Literal["paper", "physical"] = "paper"  # rule kinetics of EIC (nemsim.rules.kinetics)
    flux_gate: bool = False  # scale the update by the ion-flux gate (nemsim.model.gate): no ions, no change
    steps_per_call: int = 1  # k states predicted per call (1 = the paper's model; module docstring)
    # rollouts project each state onto x >= running max - eps, (mask, Si); None: off (nemsim.model.monotone)
    monotone_eps: tuple[float, float] | None = MONOTONE_EPS
    # Si slack on the hole-axis columns (the depth readout); None: monotone_eps there too
    monotone_axis_eps: float | None = MONOTONE_AXIS_EPS
    # (knee, limit) box half-widths: the learned parts read saturated controls; None: off (saturation.py)
    control_saturation: tuple[float, float] | None = CONTROL_SATURATION
    # line-of-sight direct flux of the four angular species as encoder input (nemsim.model.transport)
    transport_input: bool = False
    transport: TransportConfig = field(default_factory=TransportConfig)
    # the learned parts read the angular spread of the four angular species too (nemsim.model.angle_features)
    angle_features: bool = False
    # "quarter" / "section": the network runs on the fundamental domain of the scene's square symmetry, or of
    # a trench's mirror and translations (module docstring)
    domain: Literal["full", "quarter", "section"] = "full"
    full_size: int = 0  # lateral size n of the full padded field (set from the scene for a folded model)
    eic: EICConfig = field(default_factory=EICConfig)  # γ, δ_max, widths (shared dims overridden above)
    mac: MACConfig = field(default_factory=MACConfig)  # κ, ρ_max, ρ_raw init, widths
    mrc: MRCConfig = field(default_factory=MRCConfig)  # A, K init, widths

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> "NEMSimConfig":
        """Build from a partial, nested or dotted-key dict; unknown keys raise ValueError."""
        return apply_overrides(cls(), d or {})


def apply_overrides(cfg, overrides: dict[str, Any]):
    """Return a copy of dataclass ``cfg`` with ``overrides`` applied (nested dicts or "a.b" keys)."""
    nested: dict[str, Any] = {}
    for key, value in overrides.items():
        head, _, rest = key.partition(".")
        if rest:
            nested.setdefault(head, {})[rest] = value
        elif isinstance(value, dict):
            nested.setdefault(head, {}).update(value)
        else:
            nested[head] = value
    names = {f.name: f for f in dataclasses.fields(cfg)}
    changes: dict[str, Any] = {}
    for key, value in nested.items():
        if key not in names:
            raise ValueError(
                f"unknown config key {key!r} for {type(cfg).__name__}; expected one of {sorted(names)}"
            )
        current = getattr(cfg, key)
        if dataclasses.is_dataclass(current) and isinstance(value, dict):
            changes[key] = apply_overrides(current, value)
        elif isinstance(current, tuple) and isinstance(value, (list, tuple)):
            changes[key] = tuple(value)
        else:
            changes[key] = value
    return dataclasses.replace(cfg, **changes)


class NEMSim(nn.Module):
    """forward(x (B, 2, D, H, W), u (B, 14) normalized, return_aux=False) -> x̂ (B, 2, D, H, W) [, aux]."""

    def __init__(self, rules, config: NEMSimConfig | None = None) -> None:
        super().__init__()
        cfg = config or NEMSimConfig()
        if int(cfg.steps_per_call) != cfg.steps_per_call or cfg.steps_per_call < 1:
            raise ValueError(f"steps_per_call must be an integer >= 1, got {cfg.steps_per_call!r}")
        check_saturation(cfg.control_saturation)
        if cfg.domain not in ("full", "quarter", "section"):
            raise ValueError(f"domain is 'full', 'quarter' or 'section', got {cfg.domain!r}")
        if cfg.domain != "full" and cfg.full_size < 3:
            raise ValueError(f"a {cfg.domain}-domain model needs full_size (the scene's lateral size), "
                             f"got {cfg.full_size!r}")
        self.config = cfg
        self.fold: FieldFold | None = model_fold(self)
        self.rules = RuleBuffers(rules)  # fixed buffers, never parameters
        E = self.rules.n_events
        desc_dim = int(self.rules.phi.shape[1])
        n_in = N_CONTROLS + (N_ANGLE_FEATURES if cfg.angle_features else 0)  # control columns the nets read
        shared = dict(context_dim=cfg.context_dim, n_controls=n_in)
        self.encoder = StateEncoder(
            EncoderConfig(stem=cfg.stem, widths=cfg.widths, latent_channels=cfg.latent_channels,
                          context_dim=cfg.context_dim)
        )
        eic_cfg = dataclasses.replace(cfg.eic, **shared)
        if cfg.use_eic:
            self.eic: nn.Module = EventIntensityCompiler(
                eic_cfg, n_rate_desc=int(self.rules.psi.shape[1]), kinetics=cfg.kinetics
            )
        else:
            self.eic = UnstructuredIntensity(eic_cfg, E)
        self.mac = MechanismAttributionCompiler(
            dataclasses.replace(cfg.mac, n_families=cfg.n_families, desc_dim=desc_dim, **shared),
            enabled=cfg.use_mac,
        )
        self.mrc = MechanismResponseCompiler(
            dataclasses.replace(cfg.mrc, n_families=cfg.n_families, n_modes=cfg.n_modes,
                                latent_channels=cfg.latent_channels, readout_width=cfg.readout_width,
                                desc_dim=desc_dim, **shared),
            n_events=E,
            enabled=cfg.use_mrc,
        )
        self.decoder = ResidualDecoder(
            DecoderConfig(latent_channels=cfg.latent_channels, skip_channels=cfg.widths[0],
                          widths=cfg.decoder_widths, out_scale=cfg.decoder_out_scale,
                          steps=cfg.steps_per_call, refine=cfg.decoder_refine)
        )
        self.multiple = self.encoder.cfg.downsample
        if cfg.domain == "section":  # line mode (module docstring): every 3x3x3 kernel acts as its sum over y
            for m in self.modules():
                if isinstance(m, Conv3d) and m.kernel_size == (3, 3, 3):
                    m.line = True
        # transport_input: Φ (4 channels at 1/2 resolution) added to the stem's output by a 1x1x1
        # convolution that starts at zero, so a warm-started model predicts exactly what it did before
        self.transport_in: Conv3d | None = None
        if cfg.transport_input:
            conv = Conv3d(4, cfg.stem, 1)
            nn.init.zeros_(conv.weight)
            nn.init.zeros_(conv.bias)  # type: ignore[arg-type]
            self.transport_in = conv

    @property
    def rules_sha256(self) -> str:
        return self.rules.sha256

    def _pad(self, x: torch.Tensor) -> torch.Tensor:
        """Edge-pad (B, C, D, H, W) on the high side of each axis up to a multiple of 4. On the quarter domain
        the lateral high sides lie on the hole axis: they get the mirror halo of the full field there
        (``nemsim.symmetry.mirror_pad``), at least one voxel, so the convolutions see across the axis what the
        full field has (a quadrant already a multiple of 4 gets 4 more)."""
        D, H, W = x.shape[2:]
        m = self.multiple
        if self.fold is not None:  # the halo across the axis (the section's rows need none: all equal)
            x = self.fold.pad(x, (-W) % m or m)
            H, W = x.shape[-2:]
        pd, pw = (-D) % m, (-W) % m
        ph = 0 if self.fold is not None and self.fold.kind == "section" else (-H) % m  # a line: no H grid
        if pd == ph == pw == 0:
            return x
        return F.pad(x, (0, pw, 0, ph, 0, pd), mode="replicate")

    def _full_input(self, x: torch.Tensor) -> bool:
        """True when a quarter- or section-domain model is handed a full field (folded in, unfolded out)."""
        return self.fold is not None and x.dim() == 5 and self.fold.is_full(x)

    def precompute(self, u: torch.Tensor, fused: bool = True) -> dict[str, Any]:
        """Everything of one transition that depends only on the controls u (B, 14) (and the fixed rules):
        the rule kinetics λ^{p,b} and Y, EIC's control modulation, MAC's static anchor α^anc, MRC's
        signature S and A, K. A rollout with constant controls computes it once and calls ``step``.

        ``fused`` (inference): ``step`` computes the MRC increment from the trunk's Gram matrix instead of
        materializing the M·R mode fields (``MechanismResponseCompiler.fused_increment``; equal up to
        float rounding). ``forward`` uses ``fused=False``, the paper's literal form.

        With ``control_saturation`` the learned parts (and ``cache["u"]``) get the saturated controls, the
        ion-flux gate the true ones (``nemsim.model.saturation``)."""
        if u.dim() != 2 or u.shape[1] != N_CONTROLS:
            raise ValueError(f"u must be (B, {N_CONTROLS}) normalized controls, got {tuple(u.shape)}")
        u_true = u
        sat = check_saturation(self.config.control_saturation)
        if sat is not None:  # the learned parts read saturated controls (the identity in the box)
            u = saturate_controls(u, *sat)  # (B, 14)
        u_net = u
        if self.config.angle_features:  # (B, 18): the 14 controls, then the four angular spreads
            a = angle_features(u)
            u_net = torch.cat([u, saturate_controls(a, *sat) if sat is not None else a], dim=1)
        return {
            "u": u_net,  # what the learned parts read
            "eic": self.eic.precompute(u_net, self.rules),  # type: ignore[operator]
            "mac": self.mac.precompute(self.rules),
            "mrc": self.mrc.precompute(self.rules, fused=fused),
            # flux_gate: g (B, 1, 1, 1, 1) scaling the update (nemsim.model.gate)
            "gate": ion_flux_gate(u_true)[:, None, None, None, None] if self.config.flux_gate else None,
            # transport_input: species weights of the rays (B, 4, K) (nemsim.model.transport)
            "transport": species_weights(u, self.config.transport) if self.transport_in is not None else None,
        }

    def predict(self, x: torch.Tensor, cache: dict[str, Any], return_aux: bool = False,
                window: WindowRun | None = None):
        """The next k = ``config.steps_per_call`` states from x (B, 2, D, H, W) under the controls of
        ``cache = precompute(u)``: (B, k, 2, D, H, W), x̂_{t+1..t+k} [, aux]. For k = 1 this is
        ``step(x, cache)[:, None]``. ``window``: the run of a depth-windowed call (``DepthWindow`` calls
        this; x is then the window's slab). A quarter-domain model takes and returns its quadrant, or a full
        field (folded on the way in, the k states unfolded on the way out: exactly symmetric)."""
        if self._full_input(x):
            f = self.fold
            assert f is not None
            out = self.predict(f.fold(x), cache, return_aux, window)
            return (f.unfold(out[0]), out[1]) if return_aux else f.unfold(out)
        D, H, W = x.shape[2:]
        z_next, b, xp, parts = self._latent_update(x, cache, window)
        # cumulative residuals from x_t, cropped back; k = 1: the paper's Dec(z̃, b, x)
        residual = self.decoder(z_next, b, xp)[..., :D, :H, :W].to(x.dtype)  # (B, k, 2, D, H, W)
        if cache.get("gate") is not None:  # flux_gate: zero ion flux, zero update
            residual = residual * cache["gate"].to(residual.dtype).view(-1, *([1] * (residual.dim() - 1)))
        x_next = x[:, None] + residual  # eq:supp_mrc_state_update (B, k, 2, D, H, W)
        if self.config.clamp_output:
            x_next = x_next.clamp_(-1.0, 1.0)  # in place: x_next is a fresh tensor (one pass fewer)
        if self.fold is not None:  # the quadrant's diagonal mirror, the section's rows, exactly
            x_next = self.fold.finish(x_next)
        if not return_aux:
            return x_next
        lam, eic, alpha, T, amp = parts
        aux = {
            "lambda": lam, "alpha": alpha, "T": T, "S": amp["S"], "P": amp["P"], "G": amp["G"],
            "w": amp["w"], "lambda_p": eic["lam_p"], "lambda_d": eic["lam_d"], "pool": eic["pool"],
            "delta_l": eic["dl"],
        }
        return x_next, aux

    def predict_into(self, x: torch.Tensor, cache: dict[str, Any], out: torch.Tensor,
                     finish: Finish = NO_FINISH) -> torch.Tensor:
        """``predict(x, cache)[:, :n]`` written into out (B, n, 2, D, H, W), n <= k, and ``finish``ed
        (``rollout``'s fast path). Outside autograd and autocast, on float32 CPU tensors, the decoder's
        packed output becomes the finished states in one fused pass (``nemsim.model.unpack``: the same
        states, several full-size passes fewer); otherwise it is a copy of ``predict``."""
        fused = (not torch.is_grad_enabled() and not torch.is_autocast_enabled("cpu")
                 and x.device.type == "cpu" and x.dtype == out.dtype == torch.float32
                 and not self._full_input(x))
        if not fused:
            return finish.apply_(out.copy_(self.predict(x, cache)[:, : out.shape[1]]))
        return write_states(x, self.predict_packed(x, cache).float(), cache.get("gate"),
                            self.config.clamp_output, out, finish)

    def predict_packed(self, x: torch.Tensor, cache: dict[str, Any]) -> torch.Tensor:
        """The decoder's packed residuals of a call (``ResidualDecoder.packed``, padded half grid):
        (B, 16k, D'/2, H'/2, W'/2), before the states are formed. ``nemsim.model.unpack.write_states`` turns
        them into the k states (gate, + x, clamp); the OpenVINO runtime exports this method."""
        z_next, b, xp, _ = self._latent_update(x, cache, None)
        return self.decoder.packed(z_next, b, xp)

    def _latent_update(self, x: torch.Tensor, cache: dict[str, Any], window: WindowRun | None):
        """Everything of a call up to the decoder: (z̃, b, the padded input, (λ, EIC outputs, α, T, MRC
        amplitudes))."""
        u = cache["u"]
        if x.dim() != 5 or x.shape[1] != 2:
            raise ValueError(f"x must be (B, 2, D, H, W), got {tuple(x.shape)}")
        if u.shape[0] != x.shape[0]:
            raise ValueError(f"the cache holds controls for batch {u.shape[0]}, x has batch {x.shape[0]}")
        # Stability guard: states are SDF/d_max clipped to [-1, 1], so the clamp is the identity on every
        # valid state; a rollout that drifts outside no longer feeds the excess back through the network
        # (without it `nemsim stress` finds rollouts that grow without bound).
        # The output is projected onto the same range (clamp_output, see the module docstring).
        xin = x.clamp(-1.0, 1.0) if self.config.clamp_input else x
        xp = self._pad(xin)  # (B, 2, D', H', W')
        extra = None
        if self.transport_in is not None:  # Φ from the padded state: (B, 4, D'/2, H'/2, W'/2) -> stem width
            tc = self.config.transport
            extra = self.transport_in(transport_field(xp, cache["transport"], tc).mul_(tc.gain))
        z, b, z_bar = self.encoder(xp, extra)  # (B, C_z, d, h, w), (B, 12, D'/2, ..), (B, K)
        eic = self.eic(z_bar, u, self.rules, cache["eic"])
        lam = eic["lam"]  # (B, E)
        alpha = self.mac(lam, z_bar, u, self.rules, cache["mac"])  # (B, E, M)
        T = lam[:, :, None] * alpha  # (B, E, M)  eq:supp_event_mechanism_driver
        z_mrc = z if window is None else splice_latent(self.mrc, z, window)  # MRC sees the full latent grid
        dz, amp = self.mrc(z_mrc, z_bar, u, T, self.rules, cache["mrc"])  # (B, C_z, d, h, w)
        dz = dz[:, :, dz.shape[2] - z.shape[2]:]  # the window's part (all of it without a window)
        z_next = z + dz.to(z.dtype)  # eq:supp_mrc_latent_update
        return z_next, b, xp, (lam, eic, alpha, T, amp)

    def step(self, x: torch.Tensor, cache: dict[str, Any], return_aux: bool = False):
        """``forward(x, cache["u"])`` with the control-only part taken from ``cache = precompute(u)``: the
        next state (B, 2, D, H, W). With steps_per_call k > 1 it is the first of the k predicted states
        (``predict(x, cache)[:, 0]``; the other k - 1 are computed and dropped: use ``predict``)."""
        out = self.predict(x, cache, return_aux)
        if not return_aux:
            return out[:, 0]
        return out[0][:, 0], out[1]

    def forward(self, x: torch.Tensor, u: torch.Tensor, return_aux: bool = False, all_steps: bool = False):
        """x̂_{t+1} (B, 2, D, H, W); with ``all_steps`` the k states of ``predict`` (B, k, 2, D, H, W)
        (what k-step training calls, also through DDP)."""
        if x.dim() != 5 or x.shape[1] != 2:
            raise ValueError(f"x must be (B, 2, D, H, W), got {tuple(x.shape)}")
        if u.shape != (x.shape[0], N_CONTROLS):
            raise ValueError(f"u must be (B, {N_CONTROLS}) normalized controls, got {tuple(u.shape)}")
        cache = self.precompute(u, fused=False)
        return self.predict(x, cache, return_aux) if all_steps else self.step(x, cache, return_aux)
