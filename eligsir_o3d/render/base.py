"""RenderOutput and the tile-renderer skeleton that every CPU-side backend shares."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import torch

from ..core.camera import Camera
from .projection import EPS2D, TILE, Projection, TileBins, bin_tiles, project
from .sh import sh_eval, view_dirs

ALPHA_MAX = 0.999  # gsplat 1.5 clamps per-Gaussian alpha here
ALPHA_MIN = 1.0 / 255.0  # contributions below this are skipped
T_MIN = 1e-4  # compositing stops before transmittance falls to this


@dataclass
class RenderOutput:
    """One rendered view. Images are [H, W(, 3)] on the renderer's device.

    ``color``, ``depth`` and ``alpha`` agree across backends (tested against the torch reference). The per-Gaussian
    screen-space fields do not mean the same on every backend, so policies and the loss must not read them (a test
    holds ``eligsir_o3d.scheduling`` to that):

    - ``radii``: torch and cpu: ``ceil(3 sqrt(lambda_max))`` of the 2D covariance, one per Gaussian, > 0 for every
      Gaussian in front of the near plane whose 3-sigma box touches the image, whatever its opacity.
      gsplat: the larger of gsplat's per-axis extents ``ceil(e sqrt(cov_ii))`` with the opacity-aware
      ``e = min(3.33, sqrt(2 ln(255 o)))``; 0 also for Gaussians with opacity below 1/255 (gsplat skips them).
    - ``visible`` (``radii > 0``): therefore "was projected onto the image", not "contributed to a pixel": an
      on-screen Gaussian hidden behind opaque ones is visible on every backend, a nearly transparent one only on
      torch and cpu.
    - ``means2d``: projected centres in pixels with integer pixel centres (Open3D's convention) on every backend;
      NaN in the rows of culled Gaussians (``radii == 0``) on every backend (gsplat leaves them uninitialised),
      so that a consumer that forgets the ``visible`` mask fails loudly instead of reading garbage.
    """

    color: torch.Tensor  # [H, W, 3] in [0, 1], background composited
    depth: torch.Tensor  # [H, W] expected z-depth in metres (accumulated depth / alpha; 0 where alpha ~ 0)
    alpha: torch.Tensor  # [H, W] accumulated opacity
    radii: torch.Tensor  # [N] int32 screen radius; 0 = the Gaussian was culled (see the class docstring)
    means2d: torch.Tensor | None = None  # [N, 2] pixels, meaningful where visible (screen-space statistics)
    # the compositing's accumulations before finish(), for a fused loss (the cpu renderer only): colour and depth
    # summed front to back [H, W, 4], alpha [H, W] (differentiable), the background [3] or None
    raw: tuple | None = None

    @property
    def visible(self) -> torch.Tensor:  # [N] bool: projected onto the image (see the class docstring)
        return self.radii > 0


class DeferredRenderOutput(RenderOutput):
    """A :class:`RenderOutput` whose ``color`` and ``depth`` are composited from ``raw`` (:func:`finish`) when first
    read: a training update's fused loss reads only the accumulations, so it skips the background composite and
    the depth normalisation (~3 % of a 1/4-scale update of the kitchen map); anything that reads them gets the same
    tensors an eager render gives."""

    def __init__(self, alpha: torch.Tensor, radii: torch.Tensor | None, means2d: torch.Tensor | None, raw: tuple,
                 screen=None):
        # color and depth stay unset (they have no class default), so reading them reaches __getattr__ once; the
        # accumulations are kept apart from ``raw``, which a consumer may clear (then the torch loss is taken).
        # ``screen``: a function returning (radii, means2d), called when either is first read (left unset then)
        self.alpha, self.raw = alpha, raw
        self._accumulated, self._screen = raw, screen
        if screen is None:
            self.radii, self.means2d = radii, means2d

    def __getattr__(self, name: str):
        if name in ("radii", "means2d") and self.__dict__.get("_screen") is not None:
            self.radii, self.means2d = self._screen()
            return getattr(self, name)
        if name not in ("color", "depth"):
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        acc, alpha, background = self._accumulated
        self.color, self.depth, _ = finish(acc[..., :3], acc[..., 3], alpha, background)
        return getattr(self, name)

    @property
    def means2d(self):
        """The projected centres; with a ``screen`` function made (with ``radii``) when first read (a property:
        the class default of :class:`RenderOutput` would otherwise answer before ``__getattr__``)."""
        d = self.__dict__
        if "_means2d" not in d:
            self.radii, d["_means2d"] = self._screen()
        return d["_means2d"]

    @means2d.setter
    def means2d(self, value) -> None:
        self.__dict__["_means2d"] = value


def view_colors(colors: torch.Tensor, means: torch.Tensor, T_world_cam, sh_degree: int | None = None) -> torch.Tensor:
    """[N, 3] colours for the camera at ``T_world_cam``: ``colors`` itself when it is [N, 3] RGB, else [N, K, 3]
    spherical-harmonic coefficients evaluated along the viewing directions (:func:`.sh.sh_eval`, degree
    ``sh_degree`` or all that K holds). Gradients reach the coefficients and, through the directions, the means."""
    if colors.dim() == 2:
        return colors
    return sh_eval(colors, view_dirs(means, T_world_cam).to(colors.dtype), sh_degree)


def render_map(renderer, gmap, camera: Camera, T_world_cam, background=None) -> RenderOutput:
    """``gmap`` (a GaussianMap) drawn by ``renderer`` at ``camera`` / ``T_world_cam`` as users see it: with the
    map's own low-pass for that camera (:meth:`.GaussianMap.low_pass`)."""
    return renderer.render(*gmap.render_args(), camera, T_world_cam, background, low_pass=gmap.low_pass(camera))


def mask_culled(means2d: torch.Tensor, radii: torch.Tensor) -> torch.Tensor:
    """``means2d`` [N, 2] with NaN in the rows of culled Gaussians (``radii`` [N] == 0)."""
    return torch.where((radii > 0)[:, None], means2d, torch.full_like(means2d, float("nan")))


def finish(color_acc, depth_acc, alpha_acc, background) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Composite the background and normalise accumulated depth (shared by all backends)."""
    if background is not None:
        color = color_acc + (1.0 - alpha_acc)[..., None] * background
    else:
        color = color_acc
    depth = torch.where(alpha_acc > 1e-4, depth_acc / alpha_acc.clamp_min(1e-4), torch.zeros_like(depth_acc))
    return color, depth, alpha_acc


class TileRenderer(ABC):
    """Projection + tile binning in torch; ``composite`` (per-tile front-to-back blending) is the backend part."""

    name = "base"

    def __init__(self, device: str | torch.device = "cpu"):
        self.device = torch.device(device)

    def render(self, means, quats, scales, opacities, colors, camera: Camera, T_world_cam,
               background: torch.Tensor | None = None, sh_degree: int | None = None,
               low_pass: float = EPS2D) -> RenderOutput:
        """means [N, 3], quats [N, 4] wxyz, scales [N, 3] metres, opacities [N] in (0, 1), colors [N, 3] RGB or
        [N, K, 3] SH coefficients (evaluated from the camera centre, degree ``sh_degree`` or all that K holds);
        ``low_pass``: the screen-space variance [px^2] added to each Gaussian (:meth:`.GaussianMap.low_pass`)."""
        colors = view_colors(colors, means, T_world_cam, sh_degree)
        proj = project(means, quats, scales, camera, T_world_cam, low_pass)
        bins = bin_tiles(proj, camera.width, camera.height)
        color_acc, depth_acc, alpha_acc = self.composite(proj, opacities, colors, bins, camera.width, camera.height)
        if background is not None:
            background = torch.as_tensor(background, dtype=color_acc.dtype, device=color_acc.device)
        color, depth, alpha = finish(color_acc, depth_acc, alpha_acc, background)
        return RenderOutput(color, depth, alpha, proj.radii, mask_culled(proj.means2d, proj.radii))

    @abstractmethod
    def composite(self, proj: Projection, opacities, colors, bins: TileBins, width: int, height: int):
        """Return accumulated colour [H, W, 3], depth [H, W] and alpha [H, W] (no background)."""
        raise NotImplementedError


def tile_pixel_coords(bins: TileBins, device) -> torch.Tensor:
    """[T, 256, 2] pixel-centre coordinates (x, y) of every pixel slot of every tile."""
    ty, tx = torch.meshgrid(torch.arange(bins.tiles_y, device=device), torch.arange(bins.tiles_x, device=device),
                            indexing="ij")
    py, px = torch.meshgrid(torch.arange(TILE, device=device), torch.arange(TILE, device=device), indexing="ij")
    x = tx.reshape(-1, 1) * TILE + px.reshape(1, -1)
    y = ty.reshape(-1, 1) * TILE + py.reshape(1, -1)
    return torch.stack([x, y], -1).float()


def untile(values: torch.Tensor, bins: TileBins, width: int, height: int) -> torch.Tensor:
    """[T, 256, C] per-tile pixel values -> [H, W, C] image (crop the padding of edge tiles)."""
    c = values.shape[-1]
    img = values.reshape(bins.tiles_y, bins.tiles_x, TILE, TILE, c).permute(0, 2, 1, 3, 4)
    return img.reshape(bins.tiles_y * TILE, bins.tiles_x * TILE, c)[:height, :width]
