"""Frames that cannot be used: one rule for source and held-out frames of a recorded sequence.

A frame whose colour or depth file is missing, truncated or corrupt, or whose pose is invalid, raises while it is
read (:class:`~eligsir_o3d.datasets.DatasetError`, :class:`~eligsir_o3d.core.frame.FrameError`, an ``OSError``; a pose
source's ``TrackingLost``). With ``clock.on_bad_frame = "skip"`` (the default) the frame is left out with a warning
naming it, the file and the reason, and the run goes on; with ``"stop"`` the first such error ends the run.

- source frames: :meth:`MappingPipeline._frames` skips them (``skipped_frames`` in metrics.json);
- held-out frames: :func:`read_heldout` drops them from the evaluation split (``heldout_skipped`` in metrics.json:
  index, file, reason). A dropped held-out frame does not become a source frame: the split stays as it was fixed.

Held-out frames are read before mapping starts, so with ``"stop"`` a bad held-out frame ends the run before any
source frame is mapped.
"""

from __future__ import annotations

import logging

log = logging.getLogger("eligsir_o3d")

# what reading or posing a frame raises for a bad frame (DatasetError and FrameError are ValueErrors, a pose
# source's TrackingLost is a RuntimeError)
BAD_FRAME_ERRORS = (ValueError, OSError, RuntimeError)


def frame_fault(index: int, error: BaseException, on_bad_frame: str, action: str = "skipping") -> str:
    """The one-line message ``"frame <index>: <reason>"`` of a frame that cannot be used, logged as a warning
    (``"<action> <message>"``). Re-raises ``error`` when ``on_bad_frame`` is ``"stop"``."""
    if on_bad_frame == "stop":
        raise error
    text = str(error)
    msg = text if text.startswith(f"frame {index}") else f"frame {index}: {text}"
    log.warning("%s %s", action, msg)
    return msg


def fault_file(seq, index: int, message: str) -> str:
    """The file a frame's error names: its colour or depth file when the message names one, else the recording
    (an invalid pose, a registration failure: the sequence as a whole)."""
    for attr in ("depth_paths", "color_paths"):
        paths = getattr(seq, attr, None) or []
        if 0 <= index < len(paths) and str(paths[index]) in message:
            return str(paths[index])
    return str(getattr(seq, "path", ""))


def read_heldout(seq, indices, depth_max: float, on_bad_frame: str = "skip") -> tuple[list, list[dict]]:
    """(frames, skipped) of the held-out split ``indices`` of ``seq``.

    A frame that cannot be read (or whose pose is invalid) is left out of ``frames`` and recorded in ``skipped``
    as ``{"index", "file", "reason"}``, with a warning; ``on_bad_frame="stop"`` re-raises its error instead.
    Raises ValueError when not one held-out frame can be read (there would be nothing to evaluate on).
    The frames are :class:`~eligsir_o3d.eval.heldout_view.HeldoutView` s: uint8 colour and compressed depth in
    memory (about 1 MiB per 640x480 view instead of 4.9), decoded to the same float32 images when evaluated.
    """
    from ..eval.heldout_view import HeldoutView

    frames, skipped = [], []
    scale = float(getattr(seq, "depth_scale", 1000.0) or 1000.0)
    for i in indices:
        try:
            frames.append(HeldoutView(seq.frame(i, depth_max=depth_max), scale))
        except BAD_FRAME_ERRORS as e:
            msg = frame_fault(i, e, on_bad_frame, "held-out frame dropped from the evaluation:")
            reason = msg[len(f"frame {i}: "):] if msg.startswith(f"frame {i}: ") else msg
            skipped.append({"index": int(i), "file": fault_file(seq, i, msg), "reason": reason})
    if indices and not frames:
        raise ValueError(f"{getattr(seq, 'path', 'sequence')}: none of the {len(indices)} held-out frames can be "
                         f"read (the first: frame {skipped[0]['index']}: {skipped[0]['reason']})")
    return frames, skipped
