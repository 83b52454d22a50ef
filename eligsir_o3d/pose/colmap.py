"""COLMAP structure-from-motion as an offline pose source (pycolmap), with metric scale from depth.

This source is not causal: ``prepare(sequence)`` runs the whole SfM over the recorded colour images before
mapping starts (``eligsir map --pose colmap`` says so), and ``track`` only looks the result up. Steps, in a
temporary work folder (removed afterwards unless ``work_dir`` is given):

1. the colour images are linked (or, for in-memory sequences, written) as ``images/NNNNNN.<ext>``;
2. SIFT features with the sequence's own pinhole intrinsics, fixed (COLMAP's pixel centres are at +0.5, so it
   gets ``cx + 0.5, cy + 0.5``);
3. sequential matching (``overlap`` neighbours, quadratic), which suits video;
4. incremental mapping with ``init_min_tri_angle`` lowered to 4 degrees (video baselines are small); an empty
   result raises RuntimeError instead of returning nothing;
5. metric scale: the median over all keypoints with a 3D point of sensor depth / SfM depth (the 3D point's
   z in that camera), so poses come out in metres.

``model=PATH`` imports an existing COLMAP model (``cameras``, ``images``, ``points3D`` as .bin or .txt, in PATH,
PATH/sparse/0 or PATH/0) instead; its images are matched to the sequence's frames by file name (or, without a
sequence, by sorted name order), and it is scaled from depth the same way when the sequence has depth.

Poses: pycolmap's ``image.cam_from_world()`` is world-to-camera; the source returns camera-to-world, re-anchored
like the online sources: the first frame ``track`` is called for gets ``gt_pose`` (when given) or the identity.
Frames COLMAP did not register raise TrackingLost.
"""

from __future__ import annotations

import tempfile
import warnings
from pathlib import Path

import numpy as np

from ..core.camera import Camera, check_pose, invert_pose
from .base import PoseSource, TrackingLost, first_pose

_MODEL_FILES = ("cameras", "images", "points3D")


def find_model_dir(path: str | Path) -> Path | None:
    """The folder holding a COLMAP model under ``path`` (itself, sparse/N or N), or None.

    Incremental mapping can leave several models (sparse/0, sparse/1, ...) when it could not connect all images;
    the largest one is taken (the most image records), as the SfM run of :class:`ColmapPoses` itself does."""
    path = Path(path)
    if _model_files(path):
        return path
    for parent in (path / "sparse", path):
        numbered = [d for d in sorted(parent.glob("[0-9]*")) if d.is_dir() and _model_files(d)]
        if numbered:
            return max(numbered, key=lambda d: _model_files(d)[0].stat().st_size)
    return path / "sparse" if _model_files(path / "sparse") else None


def _model_files(folder: Path) -> list[Path] | None:
    """The model's files in ``folder`` (images first), .bin or .txt, or None when it holds no complete model."""
    for ext in (".bin", ".txt"):
        files = [folder / f"{name}{ext}" for name in _MODEL_FILES]
        if all(f.is_file() for f in files):
            return sorted(files, key=lambda f: f.stem != "images")
    return None


def _import_pycolmap():
    try:
        import pycolmap
    except ImportError as e:
        raise ImportError("pose source 'colmap' needs pycolmap: pip install pycolmap "
                          "(or pip install 'eligsir-o3d[pose]')") from e
    return pycolmap


class ColmapSource(PoseSource):
    """Offline SfM poses (pycolmap), metric through depth. Runs in ``prepare``, before mapping."""

    name = "colmap"
    causal = False

    def __init__(self, *, model: str | Path | None = None, work_dir: str | Path | None = None,
                 overlap: int = 10, init_min_tri_angle: float = 4.0, max_num_features: int = 4096,
                 metric_scale: bool = True, depth_max: float = 10.0, num_threads: int = -1, seed: int = 0,
                 sequence=None) -> None:
        super().__init__(sequence)
        self.model = None if model is None else Path(model)
        if self.model is not None and find_model_dir(self.model) is None:
            raise ValueError(f"pose source 'colmap': {self.model} holds no COLMAP model (cameras, images and "
                             f"points3D .bin or .txt, directly or under sparse/0)")
        self.work_dir = None if work_dir is None else Path(work_dir)
        self.overlap, self.init_min_tri_angle = int(overlap), float(init_min_tri_angle)
        self.max_num_features, self.num_threads, self.seed = int(max_num_features), int(num_threads), int(seed)
        self.use_depth_scale, self.depth_max = bool(metric_scale), float(depth_max)
        self.metric_scale = 1.0  # SfM units -> metres
        self.scale_spread = float("nan")  # median absolute deviation of the depth ratios / their median
        self.registered = 0
        self._poses: dict[int, np.ndarray] = {}  # frame index -> camera-to-SfM-world, metric
        self._anchor: np.ndarray | None = None

    # -- offline work ---------------------------------------------------------------------------------------
    def _prepare(self, sequence) -> None:
        self._anchor = None
        pycolmap = _import_pycolmap()
        level = pycolmap.logging.minloglevel
        pycolmap.logging.minloglevel = 2  # COLMAP logs every image at INFO; keep errors only
        try:
            self._prepare_quietly(pycolmap, sequence)
        finally:
            pycolmap.logging.minloglevel = level

    def _prepare_quietly(self, pycolmap, sequence) -> None:
        if self.model is not None:
            rec = pycolmap.Reconstruction(str(find_model_dir(self.model)))
            frame_of = self._match_names(rec, sequence)
        else:
            if sequence is None:
                raise ValueError("pose source 'colmap': prepare() needs the recorded sequence (SfM runs over its "
                                 "colour images before mapping)")
            tmp = None
            work = self.work_dir
            if work is None:
                tmp = tempfile.TemporaryDirectory(prefix="eligsir_colmap_")
                work = Path(tmp.name)
            try:
                rec, frame_of = self._run_sfm(pycolmap, sequence, Path(work))
            finally:
                if tmp is not None:
                    tmp.cleanup()
        poses = {}
        for image_id in rec.reg_image_ids():
            image = rec.image(image_id)
            if image.name not in frame_of:
                continue
            T_cw = np.eye(4)
            T_cw[:3, :] = np.asarray(image.cam_from_world().matrix(), dtype=np.float64)
            poses[frame_of[image.name]] = invert_pose(T_cw)
        if not poses:
            raise RuntimeError("pose source 'colmap': no registered image of the model matches a frame of the "
                           "sequence (image names differ?)")
        self.registered = len(poses)
        if self.use_depth_scale and sequence is not None:
            self.metric_scale, self.scale_spread = self._depth_scale(rec, frame_of, sequence)
        elif self.model is None or sequence is None:
            warnings.warn("pose source 'colmap': no depth to fix the scale; poses are in SfM units, not metres")
        for T in poses.values():
            T[:3, 3] *= self.metric_scale
        self._poses = poses

    def _run_sfm(self, pycolmap, sequence, work: Path):
        images, frame_of = self._stage_images(sequence, work / "images")
        db = work / "database.db"
        if db.exists():
            db.unlink()
        cam: Camera = sequence.camera
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "PINHOLE"
        reader.camera_params = f"{cam.fx},{cam.fy},{cam.cx + 0.5},{cam.cy + 0.5}"
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.num_threads = self.num_threads
        extraction.sift.max_num_features = self.max_num_features
        pycolmap.extract_features(db, images, camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                                  extraction_options=extraction)
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = self.overlap
        pycolmap.match_sequential(db, pairing_options=pairing)
        options = pycolmap.IncrementalPipelineOptions()
        options.mapper.init_min_tri_angle = self.init_min_tri_angle
        options.ba_refine_focal_length = False
        options.ba_refine_principal_point = False
        options.ba_refine_extra_params = False
        options.num_threads = self.num_threads
        options.random_seed = self.seed  # RANSAC and initial-pair sampling; a seed makes reruns agree
        (work / "sparse").mkdir(exist_ok=True)
        maps = pycolmap.incremental_mapping(db, images, work / "sparse", options)
        if not maps:
            raise RuntimeError(f"pose source 'colmap': incremental mapping failed on {len(frame_of)} images of "
                               f"{getattr(sequence, 'name', 'the sequence')!r} (no initial pair with enough "
                               f"parallax and matches; too little texture or motion?)")
        rec = max(maps.values(), key=lambda r: r.num_reg_images())
        if rec.num_reg_images() < len(frame_of):
            warnings.warn(f"pose source 'colmap': registered {rec.num_reg_images()} of {len(frame_of)} images; "
                          "the others raise TrackingLost")
        return rec, frame_of

    @staticmethod
    def _stage_images(sequence, folder: Path) -> tuple[Path, dict[str, int]]:
        """Link (or write) frame i's colour image as ``folder/NNNNNN.ext``; returns (folder, name -> index)."""
        folder.mkdir(parents=True, exist_ok=True)
        paths = getattr(sequence, "color_paths", None) or []
        frame_of = {}
        for i in range(len(sequence)):
            if paths:
                src = Path(paths[i]).resolve()
                name = f"{i:06d}{src.suffix.lower()}"
                dst = folder / name
                if not dst.exists():
                    dst.symlink_to(src)
            else:
                import open3d as o3d

                name = f"{i:06d}.png"
                o3d.t.io.write_image(str(folder / name), sequence[i].rgbd.color)
            frame_of[name] = i
        return folder, frame_of

    @staticmethod
    def _match_names(rec, sequence) -> dict[str, int]:
        names = sorted(rec.image(i).name for i in rec.image_ids()) if hasattr(rec, "image_ids") else \
            sorted(img.name for img in rec.images.values())
        paths = getattr(sequence, "color_paths", None) or [] if sequence is not None else []
        if paths:
            by_name = {}
            for i, p in enumerate(paths):
                p = Path(p)
                by_name.setdefault(p.name, i)
                by_name.setdefault(f"{p.parent.name}/{p.name}", i)
                by_name.setdefault(p.stem, i)
            frame_of = {n: by_name.get(n, by_name.get(Path(n).name, by_name.get(Path(n).stem))) for n in names}
            frame_of = {n: i for n, i in frame_of.items() if i is not None}
            if not frame_of:
                raise ValueError("pose source 'colmap': none of the model's image names "
                                 f"({', '.join(names[:3])}...) matches a colour file of the sequence")
            return frame_of
        if sequence is not None and len(names) != len(sequence):
            warnings.warn(f"pose source 'colmap': model has {len(names)} images for {len(sequence)} frames; "
                          "matching them in sorted name order")
        return {n: i for i, n in enumerate(names)}

    def _depth_scale(self, rec, frame_of: dict[str, int], sequence) -> tuple[float, float]:
        """Median of sensor depth / SfM depth over keypoints with a 3D point (and its relative MAD)."""
        ratios = []
        for image_id in rec.reg_image_ids():
            image = rec.image(image_id)
            i = frame_of.get(image.name)
            if i is None:
                continue
            depth = sequence.frame(i).depth.numpy()
            h, w = depth.shape
            T_cw = np.asarray(image.cam_from_world().matrix(), dtype=np.float64)
            xys, xyzs = [], []
            for p in image.points2D:
                if p.has_point3D():
                    xys.append(p.xy)
                    xyzs.append(rec.point3D(p.point3D_id).xyz)
            if not xys:
                continue
            uv = np.rint(np.asarray(xys) - 0.5).astype(np.int64)  # COLMAP pixel centres are at +0.5
            z_sfm = (np.asarray(xyzs) @ T_cw[:3, :3].T + T_cw[:3, 3])[:, 2]
            inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h) & (z_sfm > 0)
            z_sensor = depth[uv[inside, 1], uv[inside, 0]]
            ok = (z_sensor > 0) & (z_sensor < self.depth_max)
            ratios.append(z_sensor[ok] / z_sfm[inside][ok])
        ratios = np.concatenate(ratios) if ratios else np.zeros(0)
        if len(ratios) < 20:
            raise RuntimeError(f"pose source 'colmap': only {len(ratios)} keypoints have both a 3D point and "
                               "sensor depth; cannot recover the metric scale (pass metric_scale=False to keep "
                               "SfM units)")
        s = float(np.median(ratios))
        return s, float(np.median(np.abs(ratios - s)) / s)

    # -- lookup ------------------------------------------------------------------------------------------------
    def _track(self, index, timestamp, color, depth, camera, gt_pose):
        if not self._poses:
            raise RuntimeError("pose source 'colmap': call prepare(sequence) first (SfM runs before mapping)")
        P = self._poses.get(index)
        if P is None:
            raise TrackingLost(f"frame {index}: COLMAP did not register this image ({self.registered} of the "
                               f"sequence's frames are registered)")
        if self._anchor is None:
            self._anchor = first_pose(gt_pose) @ invert_pose(P)
        return check_pose(self._anchor @ P, f"frame {index}: colmap pose")

    def poses(self) -> dict[int, np.ndarray]:
        """All registered frames' camera-to-world poses (anchored once ``track`` has run, else SfM world)."""
        A = self._anchor if self._anchor is not None else np.eye(4)
        return {i: A @ P for i, P in sorted(self._poses.items())}
