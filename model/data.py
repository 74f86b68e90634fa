"""Dataset reader for the rendered sequences: Mitsuba (docs/data.md, scenes/exr_io.py) and
Cycles (scenes/cycles_io.py: Blender's multilayer EXRs, decoded by the service's own decoder).

Two torch datasets over one or more split directories (<data>/<generator>/<split>/<seed>/; a
list of roots is their union, e.g. both renderers' train splits):
- `CropDataset`: item = a window of `history + 1` consecutive frames of one sequence, the same
  random crop (default 128x128) in each, one dihedral augmentation (flip, rot90) applied
  consistently to images, motion vectors and normals, and a random spp level per item.
- `SequenceDataset`: item = a whole sequence, uncropped, unaugmented (validation, test).
Both return dicts of float32 tensors shaped (T, C, H, W) (T frames, oldest first) plus `reset`
(T,) = 1 on a sequence's first frame and after a camera cut, and `spp` (). Frames are read
lazily through a small per-process LRU cache, so memory stays bounded for any dataset size.
A Cycles window has the same keys, shapes and dtypes; its normals are in Cycles' camera space
(`Sequence.normal_space`), which augmentation respects. `load_window` and `augment` are
numpy-only and usable without torch.
"""

from __future__ import annotations

import json
from collections import OrderedDict
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from quietframe.model.oidn_cache import cached_oidn_output, cached_sequence_oidn_output
from quietframe.runtime.buffers import BUFFERS
from quietframe.runtime.oidn_prepass import OIDNSettings
from quietframe.runtime.sanitize import sanitize_buffer
from quietframe.scenes import cycles_io
from quietframe.scenes.exr_io import color_layer, load_frame, pass_layer

# Buffers returned by default: the model inputs (canonical names), the target, the motion mask.
DEFAULT_BUFFERS = ("color", "albedo", "normal", "depth", "motion", "motion_valid", "reference")


@dataclass
class Sequence:
    path: Path
    seed: int
    files: list[str]  # frame files, index order (Cycles: the name inside each spp folder)
    resets: list[bool]
    to_world: list[np.ndarray]  # per frame 4x4 camera-to-world (columns left, up, fwd, origin)
    spp_levels: list[int]
    passes: int  # per-sample passes stored per frame (Cycles: none)
    size: tuple[int, int] = (0, 0)  # (H, W) of its frames, from the manifest
    renderer: str = "mitsuba"
    # Space of the stored normals: Mitsuba writes world space; Cycles' Denoising Normal is camera
    # space (its kernel applies worldtocamera: x right, y up, z away from the viewer), and the
    # service passes it on as it comes, so that is what a model serving Cycles frames sees.
    normal_space: str = "world"
    references: list[int] = field(default_factory=list)  # Cycles: frame whose reference t uses


Roots = str | Path | Iterable[str | Path]


def list_sequences(root: Roots) -> list[Sequence]:
    """Finished sequences under a split directory, sorted by seed; of several directories, each
    one's in the order given."""
    if not isinstance(root, str | Path):
        return [s for r in root for s in list_sequences(r)]
    out = []
    for mpath in sorted(Path(root).glob("*/manifest.json")):
        if cycles_io.is_cycles_sequence(mpath.parent):
            if cycles_io.finished(mpath.parent):  # else still rendering
                out.append(_cycles_sequence(mpath.parent))
            continue
        m = json.loads(mpath.read_text())
        frames = sorted(m["frames"], key=lambda f: f["index"])
        if len(frames) != m["frame_count"] or not all(
            (mpath.parent / f["file"]).exists() for f in frames
        ):
            continue  # still rendering
        out.append(
            Sequence(
                path=mpath.parent,
                seed=m["seed"],
                files=[f["file"] for f in frames],
                resets=[bool(f["reset"]) for f in frames],
                to_world=[np.asarray(f["to_world"]) for f in frames],
                spp_levels=list(m["config"]["spp_levels"]),
                passes=max(m["config"]["spp_levels"]),
                size=(m["config"]["height"], m["config"]["width"]),
            )
        )
    return sorted(out, key=lambda s: s.seed)


def _cycles_sequence(folder: Path) -> Sequence:
    m = json.loads((folder / cycles_io.MANIFEST).read_text())
    n = m["frame_count"]
    return Sequence(
        path=folder,
        seed=m["seed"],
        files=[cycles_io.frame_file(t) for t in range(n)],
        resets=cycles_io.frame_resets(folder),
        to_world=[],  # not in a Cycles manifest; only normal_space="camera" would need it
        spp_levels=list(m["config"]["spp_levels"]),
        passes=0,
        size=(m["config"]["height"], m["config"]["width"]),
        renderer="cycles",
        normal_space="camera",
        references=[cycles_io.reference_frame(folder, t) for t in range(n)],
    )


class FrameCache:
    """LRU of decoded frames keyed by what was read (Mitsuba: file and layers; Cycles: inputs
    per frame and spp, references per frame); bounded by entry count."""

    def __init__(self, max_frames: int = 16) -> None:
        self.max_frames = max_frames
        self._items: OrderedDict[tuple, Any] = OrderedDict()

    def get(self, path: Path, layers: tuple[str, ...]) -> dict[str, np.ndarray]:
        return self.load((str(path), layers), lambda: load_frame(path, list(layers)))

    def load(self, key: tuple, read: Callable[[], Any]) -> Any:
        if key in self._items:
            self._items.move_to_end(key)
            return self._items[key]
        value = read()
        self._items[key] = value
        if len(self._items) > self.max_frames:
            self._items.popitem(last=False)
        return value


def _cycles_frame(seq: Sequence, t: int, spp: int, cache: FrameCache) -> dict[str, np.ndarray]:
    """Frame t of a Cycles sequence: the inputs as the service decodes the spp-`spp` file, the
    reference (the mean of the two halves) and `motion_valid`."""
    inputs = cache.load(("cycles", str(seq.path), t, spp),
                        lambda: cycles_io.load_inputs(seq.path, t, spp))
    r = seq.references[t]  # a locked-off shot's frames share one reference: cache it once
    reference = cache.load(("cycles-reference", str(seq.path), r),
                           lambda: cycles_io.load_reference(seq.path, r))
    # Mitsuba's motion_valid is the fraction of a pixel's samples visible in frame t-1 (0 on a
    # reset frame), computed by the renderer; Cycles writes no such pass. What is known is the
    # reset rule, so 0 there and 1 elsewhere: an upper bound at disocclusions, never a mask to
    # trust there. Nothing in model/ reads it (temporal.history_valid tests depth and normal).
    valid = np.full((*reference.shape[:2], 1), 0.0 if seq.resets[t] else 1.0, np.float32)
    return {**inputs, "reference": reference, "motion_valid": valid}


def check_supported(
    seq: Sequence, with_passes: bool = False, normal_space: str = "world",
    oidn: OIDNSettings | None = None,
) -> None:
    """ValueError for what a Cycles sequence cannot give (it stores no per-sample passes, and
    neither the OIDN cache nor the world-to-camera conversion read its files)."""
    if seq.renderer != "cycles":
        return
    unsupported = [name for name, asked in (
        ("with_passes", with_passes), ("oidn", oidn is not None),
        ("normal_space='camera'", normal_space == "camera")) if asked]
    if unsupported:
        raise ValueError(
            f"Cycles sequence {seq.path}: {', '.join(unsupported)} not supported (no per-sample "
            "passes are stored, the OIDN cache reads Mitsuba files only, and its normals are "
            "already Cycles camera space, z away from the viewer, taken as the service takes "
            "them); train oidn-temporal variants and passes-based runs on Mitsuba only"
        )


def _disk_layers(buffers: tuple[str, ...], spp: int, with_passes: bool, passes: int) -> tuple:
    names = [color_layer(spp) if b == "color" else b for b in buffers]
    if with_passes:
        names += [pass_layer(k) for k in range(passes)]
    return tuple(dict.fromkeys(names))


def load_window(
    seq: Sequence,
    t: int,
    history: int,
    spp: int,
    buffers: tuple[str, ...] = DEFAULT_BUFFERS,
    with_passes: bool = False,
    normal_space: str = "world",
    cache: FrameCache | None = None,
    oidn: OIDNSettings | None = None,
) -> dict[str, np.ndarray]:
    """Frames t-history..t as numpy arrays (T, H, W, C); `color` is the `spp`-sample mean. The
    model inputs go through the runtime's sanitising rule, as in serving (e.g. depth 0 where no
    ray hit becomes the frame's farthest depth).
    Frames before the sequence start repeat frame 0 (and are flagged as resets). With `oidn`,
    also `oidn`: OIDN's output of each whole frame (model/oidn_cache.py, cached on disk).
    A Cycles sequence gives the same keys (its inputs as the service decodes them); ValueError
    for what it does not support (check_supported)."""
    check_supported(seq, with_passes, normal_space, oidn)
    cache = cache or FrameCache(2 * (history + 1))  # Cycles: inputs and reference per frame
    idx = [max(i, 0) for i in range(t - history, t + 1)]
    out = {}
    if seq.renderer == "cycles":
        frames = [_cycles_frame(seq, i, spp, cache) for i in idx]
        for b in buffers:
            out[b] = np.stack([f[b] for f in frames])
    else:
        disk = (*buffers, "color", "albedo", "normal") if oidn else buffers
        names = _disk_layers(disk, spp, with_passes, seq.passes)
        frames = [cache.get(seq.path / seq.files[i], names) for i in idx]
        for b in buffers:
            name = color_layer(spp) if b == "color" else b
            out[b] = np.stack([f[name] for f in frames])
    for b in out.keys() & BUFFERS.keys():  # what serving feeds: the one sanitising rule, per
        out[b] = np.stack([sanitize_buffer(b, frame)[0] for frame in out[b]])  # whole frame
    if oidn is not None:
        if oidn.color_from:  # frame t's OIDN input depends on frames 0..t
            out["oidn"] = np.stack([cached_sequence_oidn_output(
                seq.path, seq.files, seq.resets, i, spp, oidn) for i in idx])
        else:
            out["oidn"] = np.stack([
                cached_oidn_output(seq.path, seq.files[i], spp, oidn, f[color_layer(spp)],
                                   f["albedo"], f["normal"])
                for f, i in zip(frames, idx, strict=True)])
    if with_passes:  # (T, S, H, W, 3)
        out["passes"] = np.stack(
            [np.stack([f[pass_layer(k)] for k in range(seq.passes)]) for f in frames]
        )
    if "normal" in out and normal_space == "camera":
        out["normal"] = np.stack(
            [_to_camera(n, seq.to_world[i]) for n, i in zip(out["normal"], idx, strict=True)]
        )
    out["reset"] = np.array(
        [seq.resets[i] or j < history - t for j, i in enumerate(idx)], np.float32
    )
    return out


def window_normal_space(seq: Sequence, normal_space: str = "world") -> str:
    """The space of a window's normals, as `augment` needs it: Cycles' own camera space (x right,
    y up: flips and turns act on it as on the converted Mitsuba camera space), else the one
    asked for."""
    return "camera" if seq.normal_space == "camera" else normal_space


def _to_camera(normal: np.ndarray, to_world: np.ndarray) -> np.ndarray:
    """World normals -> camera space with x right, y up, z towards the viewer."""
    left, up, fwd = to_world[:3, 0], to_world[:3, 1], to_world[:3, 2]
    basis = np.stack([-left, up, -fwd], 1)  # (3, 3): columns are the camera axes in world
    return (normal @ basis).astype(np.float32)


def augment(
    window: dict[str, np.ndarray], flip: bool, rot90: int, normal_space: str = "world"
) -> dict[str, np.ndarray]:
    """Horizontal flip then `rot90` counter-clockwise quarter turns, on arrays (T, H, W, C).

    Motion (image coordinates, y down): a flip negates x; a CCW quarter turn maps (x, y) to
    (y, -x). World-space normals and positions: a flip is a reflection of the whole scene and all
    cameras (we reflect world X, which is consistent over frames); a rotation only rolls the
    cameras, so world vectors stay. Camera-space normals (x right, y up) flip and turn with the
    image: a flip negates x, a CCW turn maps (x, y) to (-y, x); this holds for Cycles' camera
    space too (x right, y up; its z points away from the viewer, and neither touches z).
    """
    out = {}
    for name, a in window.items():
        if a.ndim < 4:
            out[name] = a
            continue
        # Spatial axes are the two before the channel axis: (..., H, W, C).
        sp = (a.ndim - 3, a.ndim - 2)
        if flip:
            a = np.flip(a, axis=sp[1])
        a = np.rot90(a, rot90 % 4, axes=sp)
        a = np.ascontiguousarray(a)
        if name == "motion":
            if flip:
                a[..., 0] *= -1
            for _ in range(rot90 % 4):
                a = np.stack([a[..., 1], -a[..., 0]], -1)
        elif name in ("normal", "position") and normal_space == "world":
            if flip:
                a[..., 0] *= -1
        elif name == "normal":
            if flip:
                a[..., 0] *= -1
            for _ in range(rot90 % 4):
                a = np.stack([-a[..., 1], a[..., 0], a[..., 2]], -1)
        out[name] = a
    return out


def _to_tensors(window: dict[str, np.ndarray]):
    import torch

    out = {}
    for name, a in window.items():
        if a.ndim >= 4:  # (..., H, W, C) -> (..., C, H, W)
            a = np.moveaxis(a, -1, -3)
        out[name] = torch.from_numpy(np.ascontiguousarray(a, np.float32))
    return out


try:
    from torch.utils.data import Dataset as _Dataset
except ImportError:  # numpy-only use (evaluation without torch): the loaders still work
    _Dataset = object


class CropDataset(_Dataset):
    """Random crops of frame windows with consistent augmentation and a random spp level.

    spp: None draws from the sequence's own stored levels per item, an int fixes it. `root`: one
    split directory or several (their union; each must hold a finished sequence). An epoch
    visits every (sequence, frame) once; randomness comes from torch's RNG, so DataLoader worker
    seeding and `torch.manual_seed` make it reproducible.
    """

    def __init__(
        self,
        root: Roots,
        crop: int = 128,
        history: int = 1,
        spp: int | None = None,
        buffers: tuple[str, ...] = DEFAULT_BUFFERS,
        with_passes: bool = False,
        augment: bool = True,
        normal_space: str = "world",
        cache_frames: int = 16,
        oidn: OIDNSettings | None = None,
    ) -> None:
        roots = [root] if isinstance(root, str | Path) else list(root)
        listed = [list_sequences(r) for r in roots]
        for r, seqs in zip(roots, listed, strict=True):  # each root of a union is wanted
            if not seqs:
                raise FileNotFoundError(f"no finished sequences under {r}")
        self.sequences = [s for seqs in listed for s in seqs]
        for seq in self.sequences:
            check_supported(seq, with_passes, normal_space, oidn)
        self.items = [(s, t) for s, seq in enumerate(self.sequences) for t in range(len(seq.files))]
        self.crop, self.history, self.spp = crop, history, spp
        self.buffers, self.with_passes = tuple(buffers), with_passes
        self.augment, self.normal_space = augment, normal_space
        self.cache = FrameCache(cache_frames)
        self.oidn = oidn

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int):
        import torch

        s, t = self.items[i]
        seq = self.sequences[s]
        rng = np.random.default_rng(int(torch.randint(0, 2**62, ()).item()))
        spp = self.spp or int(rng.choice(seq.spp_levels))
        win = load_window(
            seq, t, self.history, spp, self.buffers, self.with_passes, self.normal_space,
            self.cache, self.oidn,
        )
        h, w = win[self.buffers[0]].shape[1:3]
        ch, cw = min(self.crop, h), min(self.crop, w)
        y0, x0 = int(rng.integers(0, h - ch + 1)), int(rng.integers(0, w - cw + 1))
        win = {
            k: (v[..., y0 : y0 + ch, x0 : x0 + cw, :] if v.ndim >= 4 else v) for k, v in win.items()
        }
        if self.augment:
            rot = int(rng.integers(4)) if ch == cw else 2 * int(rng.integers(2))
            space = window_normal_space(seq, self.normal_space)
            win = augment(win, bool(rng.random() < 0.5), rot, space)
        out = _to_tensors(win)
        out["spp"] = torch.tensor(float(spp))
        return out


class SequenceDataset(_Dataset):
    """Whole sequences (T = all frames), uncropped and unaugmented, at a fixed spp."""

    def __init__(
        self,
        root: Roots,
        spp: int = 4,
        buffers: tuple[str, ...] = DEFAULT_BUFFERS,
        with_passes: bool = False,
        normal_space: str = "world",
        oidn: OIDNSettings | None = None,
    ) -> None:
        self.sequences = list_sequences(root)
        for seq in self.sequences:
            check_supported(seq, with_passes, normal_space, oidn)
        self.spp, self.buffers, self.oidn = spp, tuple(buffers), oidn
        self.with_passes, self.normal_space = with_passes, normal_space

    def __len__(self) -> int:
        return len(self.sequences)

    def __getitem__(self, i: int):
        import torch

        seq = self.sequences[i]
        n = len(seq.files)
        win = load_window(
            seq,
            n - 1,
            n - 1,
            self.spp,
            self.buffers,
            self.with_passes,
            self.normal_space,
            FrameCache(n),
            self.oidn,
        )
        out = _to_tensors(win)
        out["spp"] = torch.tensor(float(self.spp))
        out["seed"] = torch.tensor(seq.seed)
        return out
