"""Nested dataclass configuration: one place for defaults, written with every result as config.json.

One vocabulary, checked: :meth:`Config.from_dict` (config files) and :func:`apply_override` (``--set a.b=v``)
reject an unknown key with its path and the nearest valid name. Derived values (device spelling, renderer for the device) are computed
in one step, :meth:`Config.resolve`, which returns a copy.
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..budget.clock import ClockConfig
from .checks import ConfigError, checked_value
from ..core.frame import DEPTH_MAX
from ..core.gaussians import LearningRates
from ..optim.adam import AdamConfig
from ..optim.losses import LossConfig
from ..pose.loop_closure import LoopClosureConfig
from ..scheduling.fidelity import FidelityConfig
from ..scheduling.growth import GrowthConfig
from ..scheduling.fixed_work import FixedWorkConfig
from ..scheduling.keyframes import KeyframesConfig
from ..scheduling.seeding import SeedingConfig
from ..scheduling.support import SupportConfig
from ..scheduling.supervision import SupervisionConfig
from ..scheduling.view_config import ViewConfig

@dataclass
class OptimConfig:
    """The optimiser: learning rates, loss weights, Adam's constants, view culling and torch's threads."""

    lrs: LearningRates = field(default_factory=LearningRates)
    """Per-parameter learning rates (means in metres per step, the others in their stored units)."""
    loss: LossConfig = field(default_factory=LossConfig)
    """Weights of the photometric, D-SSIM and depth terms of the mapping loss."""
    adam: AdamConfig = field(default_factory=AdamConfig)
    """Adam's betas and eps (torch's Adam)."""
    refine_scale: float = 1.0
    """Supervision scale (share of the source resolution) of the post-mapping updates of ``refine()``."""
    cull: bool = True
    """An update renders, steps and relocates only the Gaussians that can reach its view; false: the whole map."""
    kernels: str = "auto"
    """The update's kernel set (``eligsir_o3d.kernels``): auto, numba, torch or fused (auto: fused on CUDA)."""
    torch_threads: int = 1
    """Torch's threads for the mapper's CPU work on small images (``runtime.threads``); 0 leaves torch's setting."""


@dataclass
class Config:
    """Everything a run is configured by, written with every result as ``config.json``."""

    device: str = "cpu"
    """Torch device the map lives on: ``cpu``, ``cuda`` or ``cuda:N``."""
    renderer: str = "auto"
    """Rasteriser: ``auto`` (gsplat on CUDA, else cpu), ``torch``, ``cpu`` or ``gsplat``."""
    sh_degree: int = 0
    """Degree of the spherical-harmonic colour of each Gaussian (0: one RGB colour)."""
    max_gaussians: int = 300_000
    """Hard cap on the map's Gaussians; growth and MCMC stop adding at it."""
    depth_scale: float = 1000.0
    """Integer depth divided by this is metres (Open3D's spelling); float depth is already metres."""
    depth_max: float = DEPTH_MAX
    """Metres; depth farther than this counts as no measurement."""
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """RGB in [0, 1] composited behind the Gaussians."""
    max_image_side: int = 16384
    """Pixels; an image file whose header declares a longer side is refused before decoding."""
    seed: int = 0
    """Random seed of every sampler in the mapper: one seed, one map."""
    ablate: tuple[str, ...] = ()
    """Mechanisms replaced by their plain policy: any of ``views``, ``fidelity``, ``growth``."""
    optim: OptimConfig = field(default_factory=OptimConfig)
    """The optimiser."""
    keyframes: KeyframesConfig = field(default_factory=KeyframesConfig)
    """The plain view policy, used when ``views`` is ablated."""
    seeding: SeedingConfig = field(default_factory=SeedingConfig)
    """The plain growth policy, used when ``growth`` is ablated."""
    views: ViewConfig = field(default_factory=ViewConfig)
    """Map-Guided View Scheduling."""
    fidelity: FidelityConfig = field(default_factory=FidelityConfig)
    """Load-Adaptive Fidelity."""
    growth: GrowthConfig = field(default_factory=GrowthConfig)
    """Targeted Geometry Growth and its 3DGS-MCMC population refinement."""
    support: SupportConfig = field(default_factory=SupportConfig)
    """The low-resolution support render that admission and growth share."""
    supervision: SupervisionConfig = field(default_factory=SupervisionConfig)
    """How update pixels are sampled: area averages or point samples, decided per run."""
    clock: ClockConfig = field(default_factory=ClockConfig)
    """The budget: clock mode, per-frame, drain and offline budgets, the cost model."""
    fixed_work: FixedWorkConfig = field(default_factory=FixedWorkConfig)
    """Per-frame fixed work that thins out as the backlog grows."""
    loops: LoopClosureConfig = field(default_factory=LoopClosureConfig)
    """Loop closure of tracked runs (a pose graph over keyframes; the map follows the corrected poses)."""

    def resolve(self, **changes) -> "Config":
        """A copy with ``changes`` (top-level fields) applied and every derived value computed, in this one
        place: the device in torch's spelling (``CUDA:0`` -> ``cuda:0``), the renderer chosen for it (``auto`` ->
        ``gsplat`` on CUDA, else ``cpu``), the ablation names checked, the clock checked. The caller's Config is
        not changed. Resolving a resolved config changes nothing."""
        import torch

        from ..budget.clock import check_clock_config
        from .checks import check_values
        from ..render import resolve_backend
        from ..scheduling import ABLATIONS

        cfg = copy.deepcopy(self)
        names = {f.name for f in dataclasses.fields(cfg)}
        for k, v in changes.items():
            if k not in names:
                raise ValueError(f"Config has no field {k!r}")
            setattr(cfg, k, v)
        try:
            device = torch.device(str(cfg.device).strip().lower())
        except RuntimeError:
            raise ValueError(f"device {cfg.device!r} is not a device name ('cpu', 'cuda', 'cuda:0', ...)") from None
        cfg.device = str(device)
        cfg.renderer = resolve_backend(cfg.renderer, device)
        unknown = [a for a in cfg.ablate if a not in ABLATIONS]
        if unknown:
            raise ValueError(f"config key ablate: unknown ablation(s) {unknown}; choose from {', '.join(ABLATIONS)}")
        cfg.ablate = tuple(cfg.ablate)
        check_clock_config(cfg.clock)
        check_values(cfg)  # NaN, negative counts, an empty map budget, a background that is not RGB
        return cfg

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def save(self, path: str | Path) -> None:
        from ..io.atomic import atomic_write_text

        atomic_write_text(path, json.dumps(self.to_dict(), indent=2))  # a full disk leaves the old file intact

    @classmethod
    def from_dict(cls, data: dict, where: str = "config") -> "Config":
        """A Config from a dict (a config file's content). Unknown keys are an error naming their path and the
        nearest valid name."""
        if not isinstance(data, dict):
            raise ConfigError(f"{where}: a config must be a JSON object, got {type(data).__name__}")
        return _build(cls, copy.deepcopy(data), where, "")

    @classmethod
    def load(cls, path: str | Path) -> "Config":
        from ..io.inputs import read_json

        path = Path(path)
        try:  # a regular file, size-capped: /dev/zero, a FIFO or a folder is one line, not a hang
            data = read_json(path, "config file")
        except ValueError as e:
            raise ConfigError(f"{e} (expected a JSON config file)") from None
        cfg = cls.from_dict(data, str(path))
        from .checks import check_values

        try:  # values no run can use (NaN, negative counts): named with the file here, not later
            check_values(cfg)
        except ValueError as e:
            raise ConfigError(f"{path}: {e}") from None
        return cfg


def _build(tp, data: Any, where: str, prefix: str):
    """Recursively rebuild dataclass ``tp`` from a dict; an unknown key is an error."""
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: {prefix.rstrip('.') or 'config'} must be an object, got {data!r}")
    fields = {f.name: f for f in dataclasses.fields(tp)}
    for key in data:
        if key not in fields:
            raise ConfigError(f"{where}: unknown key {prefix + key!r}{_nearest(key, fields, prefix)}")
    kwargs = {}
    for name, f in fields.items():
        if name not in data:
            continue
        default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
        value = data[name]
        if dataclasses.is_dataclass(default):
            value = _build(type(default), value, where, f"{prefix}{name}.")
        else:
            value = checked_value(default, value, where, prefix + name)
        kwargs[name] = value
    return tp(**kwargs)


def _nearest(key: str, names, prefix: str) -> str:
    close = difflib.get_close_matches(key, list(names), n=1, cutoff=0.5)
    return f"; did you mean {prefix + close[0]!r}?" if close else f"; valid keys here: {', '.join(sorted(names))}"


def apply_override(cfg: Config, item: str) -> None:
    """``--set KEY=VALUE`` on ``cfg`` (see :func:`_apply_override`); its error is one line even when the item
    holds a line break (shown escaped)."""
    try:
        _apply_override(cfg, item)
    except ValueError as e:
        text = str(e)
        if "\n" in text or "\r" in text:
            raise type(e)(text.replace("\r", "\\r").replace("\n", "\\n")) from None
        raise


def _apply_override(cfg: Config, item: str) -> None:
    """Apply ``a.b.c=value`` to ``cfg`` in place; the value is parsed as JSON when it can be (``16``, ``true``,
    ``[0.25, 1]``), else taken as a string. An unknown key is a ValueError naming the nearest valid one."""
    key, eq, raw = item.partition("=")
    key = key.strip()
    if not eq or not key:
        raise ValueError(f"--set {item!r}: expected KEY=VALUE, e.g. views.active_size=16")
    try:
        value = json.loads(raw)
    except json.JSONDecodeError:
        value = raw
    *path, last = key.split(".")
    obj, prefix = cfg, ""
    for name in path + [last]:
        if not dataclasses.is_dataclass(obj):
            raise ValueError(f"--set {item}: {prefix.rstrip('.')} is a value, not a section")
        names = [f.name for f in dataclasses.fields(obj)]
        if name not in names:
            raise ValueError(f"--set {item}: unknown key {prefix + name!r}{_nearest(name, names, prefix)}")
        if prefix.count(".") < len(path):
            obj, prefix = getattr(obj, name), prefix + name + "."
    old = getattr(obj, last)
    if dataclasses.is_dataclass(old):
        raise ValueError(f"--set {item}: {key} is a section; set one of its keys ({key}.<name>=...)")
    if isinstance(old, tuple) and isinstance(value, list):
        value = tuple(value)
    elif isinstance(old, bool) and not isinstance(value, bool):
        raise ValueError(f"--set {item}: {key} takes true or false")
    elif isinstance(old, float) and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    elif old is not None and not isinstance(value, type(old)) and not (isinstance(old, float) and
                                                                       isinstance(value, float)):
        raise ValueError(f"--set {item}: {key} takes a {type(old).__name__}, got {raw!r}")
    setattr(obj, last, value)


def _guard_sections(cls: type, seen: set) -> None:
    """Make ``cls`` and every config section below it reject assignments to names they do not have, so that a
    misspelt setting (``cfg.optim.updates_per_frame = 4``: the key is ``cfg.clock.updates_per_frame``) fails
    loudly instead of being silently ignored."""
    if cls in seen or cls.__dataclass_params__.frozen:
        return
    seen.add(cls)
    names = {f.name for f in dataclasses.fields(cls)}

    def __setattr__(self, name: str, value: Any, _names=names, _cls=cls) -> None:
        if name not in _names and not name.startswith("_"):
            raise AttributeError(f"{_cls.__name__} has no setting {name!r}{_nearest(name, _names, '')}")
        object.__setattr__(self, name, value)

    cls.__setattr__ = __setattr__
    for f in dataclasses.fields(cls):
        default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
        if dataclasses.is_dataclass(default) and not isinstance(default, type):
            _guard_sections(type(default), seen)


_guard_sections(Config, set())
