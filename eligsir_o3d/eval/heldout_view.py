"""HeldoutView: a held-out frame kept compactly in memory, decoded to float32 only while it is evaluated.

The evaluation split is held for the whole run (every checkpoint renders every held-out view), so a float32
:class:`~eligsir_o3d.core.frame.Frame` per view (colour [H, W, 3] + depth [H, W]: 4.9 MiB at 640x480) made the split
grow with the recording (125 views: ~0.9 GiB with their regional samples). A HeldoutView keeps

- colour as uint8 [H, W, 3] (0.88 MiB at 640x480) when the frame's float colour is exactly ``uint8 / 255`` (colour
  read from 8-bit files always is), else the float32 colour as given;
- depth as zlib-compressed integer codes (uint16 ``round(depth * depth_scale)``) when ``code / depth_scale`` gives
  the float32 depth back bit for bit (depth read from 16-bit files always does), else its float32 bytes,
  compressed likewise (lossless either way; ~0.1 MiB for a 7-Scenes view).

:attr:`color` and :attr:`depth` decode to exactly the float32 tensors of the Frame it was made from, so every
figure computed from them is unchanged. Each access decodes afresh (a few ms at 640x480): take them once per
evaluation of a view (``color, depth = view.decoded()``).
"""

from __future__ import annotations

import zlib

import numpy as np
import torch

from ..core.frame import Frame

ZLIB_LEVEL = 1  # fastest: depth codes compress ~6x at level 1 already, higher levels gain little and cost 2x


class HeldoutView:
    """A held-out observation (colour, depth, camera, pose, timestamp, index) stored compactly; see the module.

    Attributes as a Frame's: ``camera``, ``T_world_cam`` ([4, 4] float64, may be reassigned: tracking and the
    training-pose alignment move it), ``timestamp``, ``index``; ``color`` [H, W, 3] float32 in [0, 1] and ``depth``
    [H, W] float32 metres are decoded on access.
    """

    __slots__ = ("camera", "T_world_cam", "timestamp", "index", "shape", "_color", "_depth", "_depth_dtype",
                 "_depth_scale")

    def __init__(self, frame: Frame, depth_scale: float = 1000.0):
        self.camera, self.T_world_cam = frame.camera, frame.T_world_cam
        self.timestamp, self.index = float(frame.timestamp), int(frame.index)
        color = frame.color.detach().cpu().contiguous()
        depth = frame.depth.detach().cpu().contiguous()
        self.shape = tuple(depth.shape)  # (H, W)
        self._color = _compact_color(color)
        self._depth, self._depth_dtype, self._depth_scale = _compact_depth(depth.numpy(), float(depth_scale))

    @classmethod
    def from_frame(cls, frame, depth_scale: float = 1000.0) -> "HeldoutView":
        """``frame`` as a HeldoutView (a HeldoutView is returned as it is)."""
        return frame if isinstance(frame, HeldoutView) else cls(frame, depth_scale)

    @property
    def color(self) -> torch.Tensor:
        """[H, W, 3] float32 in [0, 1], bit-identical to the source Frame's colour."""
        c = self._color
        return c.float() / 255.0 if c.dtype == torch.uint8 else c.clone()

    @property
    def depth(self) -> torch.Tensor:
        """[H, W] float32 metres (0 = no measurement), bit-identical to the source Frame's depth."""
        raw = np.frombuffer(zlib.decompress(self._depth), dtype=self._depth_dtype).reshape(self.shape)
        if self._depth_dtype == np.uint16:
            return torch.from_numpy(raw.astype(np.float32) / self._depth_scale)
        return torch.from_numpy(raw.copy())

    def decoded(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(colour [H, W, 3], depth [H, W]) float32, decoded once."""
        return self.color, self.depth

    def to_frame(self) -> Frame:
        """A full float32 Frame of this view (for code that needs one, e.g. resampling)."""
        color, depth = self.decoded()
        return Frame(color, depth, self.camera, self.T_world_cam, self.timestamp, self.index)

    @property
    def nbytes(self) -> int:
        """Bytes this view holds for its images (colour storage + compressed depth)."""
        return int(self._color.numel() * self._color.element_size()) + len(self._depth)

    def __repr__(self) -> str:
        return (f"HeldoutView(index={self.index}, {self.shape[1]}x{self.shape[0]}, colour {self._color.dtype}, "
                f"depth {np.dtype(self._depth_dtype).name}, {self.nbytes / 2**20:.2f} MiB)")


def _compact_color(color: torch.Tensor) -> torch.Tensor:
    """uint8 codes of float colour when ``code / 255`` is the colour bit for bit; else the float32 colour."""
    color = color.to(torch.float32)
    codes = torch.round(color * 255.0).clamp_(0, 255).to(torch.uint8)
    if torch.equal(codes.float() / 255.0, color):
        return codes
    return color.clone()


def _compact_depth(depth: np.ndarray, depth_scale: float) -> tuple[bytes, type, float]:
    """(zlib bytes, dtype of the raw array, scale): uint16 codes when ``code / scale`` is the depth bit for bit."""
    depth = np.ascontiguousarray(depth, dtype=np.float32)
    if depth_scale > 0 and np.isfinite(depth_scale):
        scaled = np.round(depth.astype(np.float64) * depth_scale)
        if scaled.size == 0 or (scaled.min() >= 0 and scaled.max() <= np.iinfo(np.uint16).max):
            codes = scaled.astype(np.uint16)
            if np.array_equal(codes.astype(np.float32) / depth_scale, depth):
                return zlib.compress(codes.tobytes(), ZLIB_LEVEL), np.uint16, depth_scale
    return zlib.compress(depth.tobytes(), ZLIB_LEVEL), np.float32, 1.0
