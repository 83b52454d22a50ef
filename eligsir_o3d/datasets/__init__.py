"""Dataset readers: TUM RGB-D, NICE-SLAM Replica, a plain folder layout, RealSense and ROS 1/2 bags, ScanNet
.sens files and the built-in synthetic room.

``open_sequence(path_or_name)`` detects the layout and returns an :class:`RGBDSequence`; ``seq[i]`` is a
:class:`SequenceFrame` (Open3D RGBD image, ground-truth pose, timestamp) and ``seq.frame(i)`` a :class:`Frame`.
"""

from .base import DatasetError, RGBDSequence, SequenceFrame
from .registry import list_formats, open_sequence, register_format
from .synthetic import SyntheticRoom

__all__ = ["DatasetError", "RGBDSequence", "SequenceFrame", "SyntheticRoom", "list_formats", "open_sequence",
           "register_format"]
