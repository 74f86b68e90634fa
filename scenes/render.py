"""Sequence renderer: one scene load per sequence, the camera moved per frame through
`mi.traverse`, S one-sample passes per frame (radiance + AOVs, independent seeds), an
independent-seed reference, motion vectors, one EXR per frame and a JSON manifest.
A locked-off sequence (`RenderConfig.locked_off`: static camera and scene, noise animated per
frame) renders one reference, for frame 0, and writes it into every frame.

Resumable: a frame counts as done when its EXR exists and the manifest lists it; EXRs are
written atomically. Deterministic: every seed derives from (sequence seed, frame, pass), and the
previous frame's AOVs used for the visibility test are the half-precision values on disk.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from . import exr_io, preview
from .camera import Camera, motion_for_pass
from .generator import GENERATOR_VERSION, LOCKED_OFF_REFERENCE_SCALE, generate, locked_off, summary
from .manifest import MANIFEST, open_sequence, write_json
from .mitsuba_scene import Mover, build, movers_of, set_frame, shape_index
from .mitsuba_trace import render_passes, render_reference, sampler_seed

LUMA = preview.LUMA


@dataclass
class RenderConfig:
    width: int = 256
    height: int = 256
    frames: tuple[int, int] = (8, 16)  # inclusive range; the count per sequence is seeded
    spp_levels: tuple[int, ...] = (1, 2, 4, 8)  # stored noisy means; passes = max level
    reference_spp: int = 1024
    max_depth: int = 8  # path length for passes and reference alike
    variant: str = "auto"
    extra: dict = field(default_factory=dict)
    locked_off: bool = False  # every frame frame 0's camera and poses (flicker shots)

    @property
    def passes(self) -> int:
        return max(self.spp_levels)

    @property
    def reference_samples(self) -> int:
        """Samples of a stored reference: a locked-off sequence's one reference gets more."""
        return self.reference_spp * (LOCKED_OFF_REFERENCE_SCALE if self.locked_off else 1)

    def key(self) -> dict:
        """What must match for a resumed sequence to continue the same data."""
        d = asdict(self)
        d.pop("variant")
        d.pop("extra")
        if not d["locked_off"]:  # absent when False: manifests from before it still resume
            d.pop("locked_off")
        d["frames"] = list(d["frames"])
        d["spp_levels"] = list(d["spp_levels"])
        return d


# ---------------------------------------------------------------------------------------------
# Mitsuba set-up


AOVS = "albedo:albedo,normal:sh_normal,depth:depth,position:position,shape:shape_index"


def load_scene(desc: dict, cfg: RenderConfig):
    """Mitsuba scene with the AOV integrator; also the reference integrator and overrides."""
    import mitsuba as mi

    scene_dict, overrides = build(desc)
    cam = Camera(**desc["cameras"][0])
    scene_dict["sensor"] = {
        "type": "perspective",
        "fov_axis": "x",
        "fov": cam.fov_x,
        "near_clip": 0.01,
        "to_world": mi.ScalarTransform4f(cam.to_world()),
        "sampler": {"type": "independent", "sample_count": 1},
        # Box filter: each one-sample pass is a pixel-integral sample, AOVs align with radiance.
        "film": {
            "type": "hdrfilm",
            "width": cfg.width,
            "height": cfg.height,
            "rfilter": {"type": "box"},
            "pixel_format": "rgb",
        },
    }
    path = {"type": "path", "max_depth": cfg.max_depth, "rr_depth": 5}
    scene_dict["integrator"] = {"type": "aov", "aovs": AOVS, "radiance": path}
    scene = mi.load_dict(scene_dict)
    reference = mi.load_dict(path)
    table = {k: overrides[name] for k, name in shape_index(scene).items() if name in overrides}
    return scene, reference, table


# ---------------------------------------------------------------------------------------------
# One sequence


def frame_count(seed: int, cfg: RenderConfig) -> int:
    lo, hi = cfg.frames
    return int(np.random.default_rng([seed, 1]).integers(lo, hi + 1))


def _hit_mean(values: list[np.ndarray], hits: list[np.ndarray]) -> np.ndarray:
    """Mean over the passes whose sample hit geometry (0 where none did)."""
    w = np.stack(hits).astype(np.float32)
    v = np.stack(values)
    w = w[..., None] if v.ndim == w.ndim + 1 else w
    return (np.sum(v * w, 0) / np.maximum(np.sum(w, 0), 1)).astype(np.float32)


def _half(a: np.ndarray) -> np.ndarray:
    return a.astype(np.float16).astype(np.float32)


def choose_scene(
    seed: int, n_frames: int, cfg: RenderConfig, tries: int = 8, scene_fn: Callable = generate
):
    """Generate and load the scene, rejecting seeds whose shots start blocked or almost black
    (an 8-spp preview of each shot's first frame: < 20% of pixels got any light). Also fixes
    the exposure and measures how much of the light is direct (paths of one bounce)."""
    import mitsuba as mi

    made: dict = {}

    def shot_previews(attempt: int):
        desc = scene_fn(seed, n_frames, attempt)
        if cfg.locked_off:
            desc = locked_off(desc)
        scene, reference, table = load_scene(desc, cfg)
        made.update(desc=desc, scene=scene, reference=reference, table=table)
        movers = movers_of(scene, desc)
        for shot in desc["shots"]:
            t = shot["first_frame"]
            set_frame(scene, Camera(**desc["cameras"][t]), movers, t)
            made["passes"] = passes = render_passes(
                scene, reference, sampler_seed(seed, attempt, 99), preview.PREVIEW_SPP, table)
            rad = np.mean([p["radiance"] for p in passes], 0) @ LUMA
            yield rad, np.where(passes[0]["hit"], passes[0]["depth"], np.inf)

    attempt, lum = preview.first_acceptable(seed, tries, shot_previews)
    desc, scene, reference, table, passes = (
        made[k] for k in ("desc", "scene", "reference", "table", "passes"))
    exposure, clip = preview.exposure(lum, seed)
    # Direct light only (emitters seen directly or after one bounce) on the last previewed
    # shot: the share of the image it explains says whether the scene is lit indirectly.
    direct = mi.load_dict({"type": "path", "max_depth": 2})
    img = np.array(mi.render(scene, integrator=direct, seed=sampler_seed(seed, 98),
                             spp=preview.PREVIEW_SPP))
    d_lum = np.nan_to_num(np.asarray(img, np.float32)[..., :3] @ LUMA)
    black = np.mean(passes[0]["radiance"].max(-1) <= 0)
    stats = preview.lighting_stats(d_lum, lum[-1], clip, black)
    return desc, scene, reference, table, attempt, exposure, stats


def render_sequence(
    seed: int,
    out_dir: str | Path,
    cfg: RenderConfig,
    on_frame: Callable[[int, dict], None] | None = None,
    scene_fn: Callable[[int, int, int], dict] = generate,
) -> dict:
    """Render (or finish) sequence `seed` into out_dir; returns the manifest. `scene_fn`
    (seed, frames, attempt) -> description replaces the generator (tests pin cameras); a
    locked-off config renders `locked_off` of its description."""
    import mitsuba as mi

    out = Path(out_dir)
    mpath = out / MANIFEST
    manifest = open_sequence(out, cfg.key())
    n_frames = frame_count(seed, cfg)
    done = {f["index"] for f in (manifest or {}).get("frames", []) if (out / f["file"]).exists()}
    if manifest and len(done) == n_frames:
        return manifest

    t0 = time.perf_counter()
    desc, scene, reference, table, attempt, exposure, stats = choose_scene(
        seed, n_frames, cfg, scene_fn=scene_fn
    )
    movers = movers_of(scene, desc)
    if manifest is None or manifest.get("attempt") != attempt:
        manifest = {
            "generator": GENERATOR_VERSION,
            "seed": seed,
            "attempt": attempt,
            "variant": mi.variant(),
            "config": cfg.key(),
            "locked_off": cfg.locked_off,
            "frame_count": n_frames,
            "exposure": exposure,  # radiance scale applied to passes and reference
            "summary": summary(desc),
            # 1-bounce share of the preview's light, black 1-spp pixels: indirect lighting.
            "lighting_stats": stats,
            "cuts": desc["cuts"],
            "scene_setup_s": time.perf_counter() - t0,
            "frames": [],
            "scene": desc,
        }
    exposure = manifest["exposure"]
    cams = [Camera(**c) for c in desc["cameras"]]
    resets = {0, *desc["cuts"]}
    prev = None
    # Locked-off: frame 0's reference (exposed, as stored) for every frame; a resumed sequence
    # takes it from frame 0's EXR rather than rendering it again.
    shared_ref = None
    if cfg.locked_off and 0 in done:
        shared_ref = exr_io.load_frame(out / "frame_0000.exr", ["reference"])["reference"]
    for t in range(n_frames):
        fname = f"frame_{t:04d}.exr"
        if t in done:
            prev = None
            continue
        if t not in resets and prev is None:  # resuming: t-1 from disk, exactly as written
            prev = exr_io.load_frame(
                out / f"frame_{t - 1:04d}.exr", ["position", "normal", "depth"]
            )
        record, prev, ref_layer = _render_frame(
            scene,
            reference,
            table,
            movers,
            cams,
            t,
            t in resets,
            prev,
            seed,
            exposure,
            cfg,
            out / fname,
            shared_ref,
        )
        if cfg.locked_off:
            shared_ref = ref_layer
        manifest["frames"] = [f for f in manifest["frames"] if f["index"] != t] + [record]
        manifest["frames"].sort(key=lambda f: f["index"])
        write_json(mpath, manifest)
        if on_frame:
            on_frame(t, record)
    return manifest


def _object_motion(
    p: dict, movers: list[Mover], t: int
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Where each pass sample's surface point was at t-1, and its normal then: samples on a
    moving object are carried back by the object's rigid motion M(t-1) M(t)^-1."""
    if not movers:
        return None, None
    pos, nrm = p["position"].copy(), p["normal"].copy()
    for m in movers:
        on = p["shape"] == m.key
        if not on.any():
            continue
        back = m.frames[t - 1] @ np.linalg.inv(m.frames[t])
        pos[on] = pos[on] @ back[:3, :3].T + back[:3, 3]
        nrm[on] = nrm[on] @ np.linalg.inv(back[:3, :3])  # normals: inverse transpose
    return pos, nrm


def _render_frame(
    scene, reference, table, movers, cams, t, reset, prev, seed, exposure, cfg, path,
    shared_ref: np.ndarray | None = None,
):
    """Render and write frame t; returns its manifest record, the buffers frame t+1's motion
    compares with, and the (exposed) reference layer written. `shared_ref` is written as the
    reference instead of rendering one (a locked-off sequence's frame 0 reference)."""
    cam = cams[t]
    tp, cpu0 = time.perf_counter(), time.process_time()
    set_frame(scene, cam, movers, t)
    passes = render_passes(scene, reference, sampler_seed(seed, t), cfg.passes, table)
    t_passes = time.perf_counter() - tp
    tr = time.perf_counter()
    ref_dropped = 0
    if shared_ref is None:
        ref, ref_dropped = render_reference(
            scene, reference, sampler_seed(seed, t, 1_000_003), cfg.reference_samples
        )
        shared_ref = ref * exposure
    t_ref = time.perf_counter() - tr

    tw = time.perf_counter()
    hits = [p["hit"] for p in passes]
    layers = {exr_io.pass_layer(k): p["radiance"] * exposure for k, p in enumerate(passes)}
    for n in cfg.spp_levels:
        layers[exr_io.color_layer(n)] = (
            np.mean([p["radiance"] for p in passes[:n]], 0, dtype=np.float64).astype(np.float32)
            * exposure
        )
    layers["reference"] = shared_ref
    layers["albedo"] = np.mean([p["albedo"] for p in passes], 0)
    for name in ("normal", "depth", "position"):
        layers[name] = _hit_mean([p[name] for p in passes], hits)
    h, w = cfg.height, cfg.width
    if reset or prev is None:
        motion, valid = np.zeros((h, w, 2), np.float32), np.zeros((h, w), np.float32)
    else:
        per_pass = [
            motion_for_pass(
                p["position"],
                p["hit"],
                p["normal"],
                cam,
                cams[t - 1],
                prev["position"],
                prev["normal"],
                prev["depth"][..., 0] > 0,
                *_object_motion(p, movers, t),
            )
            for p in passes
        ]
        motion = np.mean([m for m, _ in per_pass], 0).astype(np.float32)
        valid = np.mean([v for _, v in per_pass], 0).astype(np.float32)
    layers["motion"], layers["motion_valid"] = motion, valid
    meta = {
        "generator": GENERATOR_VERSION,
        "seed": seed,
        "frame": t,
        "reset": bool(reset),
        "spp_levels": list(cfg.spp_levels),
        "passes": cfg.passes,
        "reference_spp": cfg.reference_samples,
        "locked_off": cfg.locked_off,
        "reference_frame": 0 if cfg.locked_off else t,
        "camera": cam.as_dict(),
        "world_to_pixel": cam.world_to_pixel(w, h).tolist(),
        "to_world": cam.to_world().tolist(),
    }
    exr_io.write_frame(path, layers, meta)
    t_write = time.perf_counter() - tw
    record = {
        "index": t,
        "file": path.name,
        "reset": bool(reset),
        "camera": cam.as_dict(),
        "to_world": cam.to_world().tolist(),
        "world_to_pixel": meta["world_to_pixel"],
        "passes_s": round(t_passes, 3),
        "reference_s": round(t_ref, 3),
        "write_s": round(t_write, 3),
        "cpu_s": round(time.process_time() - cpu0, 2),  # this process, all its threads
        "motion_valid_mean": float(valid.mean()),
        # Non-finite samples replaced by 0 (passes, reference); should stay ~0.
        "dropped_samples": [sum(p["dropped"] for p in passes), ref_dropped],
    }
    prev_next = {k: _half(layers[k]) for k in ("position", "normal")}
    prev_next["depth"] = _half(layers["depth"])[..., None]
    return record, prev_next, shared_ref
