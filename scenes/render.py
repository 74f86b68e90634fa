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

import glob
import json
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from . import exr_io, preview
from .camera import Camera, motion_for_pass
from .generator import (
    GENERATOR_VERSION,
    LOCKED_OFF_REFERENCE_SCALE,
    build,
    generate,
    locked_off,
    mover_meshes,
    summary,
)
from .manifest import MANIFEST, open_sequence, write_json

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
    locked_off: bool = False  # every frame frame 0's camera and poses (flicker shots, issue 24)

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


def _find_llvm() -> str | None:
    # drjit needs LLVM >= 16 here (14/15 fail); prefer the newest found.
    cands = glob.glob("/usr/lib/x86_64-linux-gnu/libLLVM-*.so") + glob.glob(
        "/usr/lib/llvm-*/lib/libLLVM*.so*"
    )

    def version(p: str) -> int:
        digits = "".join(ch if ch.isdigit() else " " for ch in Path(p).name).split()
        return int(digits[0]) if digits else 0

    good = [p for p in cands if version(p) >= 16]
    return max(good, key=version) if good else None


def set_variant(name: str = "auto") -> str:
    """Activate `llvm_ad_rgb` when a usable LLVM exists (about 2x faster here), else
    `scalar_rgb`. Returns the active variant."""
    if name in ("auto", "llvm_ad_rgb") and "DRJIT_LIBLLVM_PATH" not in os.environ:
        lib = _find_llvm()
        if lib:
            os.environ["DRJIT_LIBLLVM_PATH"] = lib
    import mitsuba as mi

    if name != "auto":
        mi.set_variant(name)
        return name
    try:
        mi.set_variant("llvm_ad_rgb")
        import drjit as dr

        dr.eval(dr.llvm.Float(1.0) + 1.0)  # fails here when the LLVM library is unusable
        return "llvm_ad_rgb"
    except Exception:  # noqa: BLE001 - any backend failure means: use the CPU scalar variant
        mi.set_variant("scalar_rgb")
        return "scalar_rgb"


def _seed(*parts: int) -> int:
    """A 31-bit Mitsuba sampler seed from a tuple of ints (stable across runs and machines)."""
    return int(np.random.SeedSequence(list(parts)).generate_state(1)[0] & 0x7FFFFFFF)


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


def shape_index(scene) -> dict[int, str]:
    """The per-sample shape channel's value -> shape id: the registry id in JIT variants, the
    1-based position in `scene.shapes()` in scalar ones (what the `aov` integrator writes)."""
    import mitsuba as mi

    shapes = scene.shapes()
    if mi.variant().startswith("scalar"):
        return {i + 1: s.id() for i, s in enumerate(shapes)}
    import drjit as dr

    ids = np.array(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(shapes)))
    return {int(i): s.id() for i, s in zip(ids, shapes, strict=True)}


@dataclass
class Mover:
    """A moving part: its shape-channel value, Mitsuba id, object-space mesh, per-frame 4x4."""

    key: int
    name: str
    mesh: object
    frames: list[np.ndarray]


def movers_of(scene, desc: dict) -> list[Mover]:
    names = {name: key for key, name in shape_index(scene).items()}
    return [Mover(names[n], n, m, f) for n, m, f in mover_meshes(desc) if n in names]


def set_frame(scene, cam: Camera, movers: list[Mover], t: int) -> None:
    """Camera and moving objects of frame t (one parameter update: one BVH rebuild)."""
    import mitsuba as mi

    params = mi.traverse(scene)
    params["sensor.to_world"] = mi.Transform4f(cam.to_world())
    params["sensor.x_fov"] = cam.fov_x
    for m in movers:
        placed = m.mesh.transformed(m.frames[t])
        params[f"{m.name}.vertex_positions"] = np.ascontiguousarray(placed.positions).ravel()
        params[f"{m.name}.vertex_normals"] = np.ascontiguousarray(placed.normals).ravel()
    params.update()


def render_passes(
    scene, path, seed: int, passes: int, albedo_table: dict[int, list[float]]
) -> list[dict[str, np.ndarray]]:
    """`passes` one-sample passes: radiance and AOVs per pass, (H, W, C) float32 each.

    JIT variants trace all passes as one wavefront (one lane per pixel and pass) with the path
    integrator and a primary-ray intersection for the AOVs: per-`mi.render` overhead (tracing,
    two launches in the `aov` integrator) made separate renders ~4x slower here. The scalar
    variant (CI) renders pass by pass with the scene's `aov` integrator; both define the AOVs
    the same way (albedo = BSDF diffuse reflectance, depth = ray distance t, 0 on a miss).
    """
    import mitsuba as mi

    if mi.variant().startswith("scalar"):
        imgs = [
            np.array(mi.render(scene, seed=_seed(seed, k), spp=1), np.float32)
            for k in range(passes)
        ]
    else:
        imgs = list(_trace_passes(scene, path, seed, passes))
    out = []
    for img in imgs:
        p = {
            "radiance": img[..., 0:3],
            "albedo": img[..., 3:6].copy(),
            "normal": img[..., 6:9],
            "depth": img[..., 9],
            "position": img[..., 10:13],
        }
        shape = np.rint(img[..., 13]).astype(np.int64)
        for sid, rgb in albedo_table.items():
            p["albedo"][shape == sid] = rgb
        p["shape"] = np.where(img[..., 9] > 0, shape, -1)
        p["hit"] = p["depth"] > 0
        p["dropped"] = int(img[..., 14].sum()) if img.shape[-1] > 14 else 0
        out.append(p)
    return out


def _trace_passes(scene, path, seed: int, passes: int) -> np.ndarray:
    """(passes, H, W, 14) per-sample channels, the same layout the `aov` integrator writes.
    Non-finite radiance samples (rare; e.g. degenerate shading frames) become 0, and the number
    of them is counted by the caller from the returned mask channel."""
    import drjit as dr
    import mitsuba as mi

    sensor = scene.sensors()[0]
    w, h = sensor.film().crop_size()
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(seed, w * h * passes)
    pix = dr.arange(mi.UInt32, w * h * passes) % (w * h)  # lane = pass * W*H + pixel
    film_pos = mi.Vector2f(mi.Float(pix % w), mi.Float(pix // w)) + sampler.next_2d()
    ray, _ = sensor.sample_ray_differential(
        0.0, sampler.next_1d(), film_pos / mi.ScalarVector2f(w, h), sampler.next_2d()
    )
    si = scene.ray_intersect(ray)
    albedo = si.bsdf(ray).eval_diffuse_reflectance(si)
    radiance, _, _ = path.sample(scene, sampler, ray, None, True)
    finite = dr.isfinite(radiance.x) & dr.isfinite(radiance.y) & dr.isfinite(radiance.z)
    hit = si.is_valid()
    n, p = si.sh_frame.n, si.p
    chans = [
        *(dr.select(finite, c, 0.0) for c in (radiance.x, radiance.y, radiance.z)),
        *(dr.select(hit, c, 0.0) for c in (albedo.x, albedo.y, albedo.z, n.x, n.y, n.z)),
        dr.select(hit, si.t, 0.0),
        *(dr.select(hit, c, 0.0) for c in (p.x, p.y, p.z)),
        dr.select(hit, mi.Float(dr.reinterpret_array(mi.UInt32, si.shape)), 0.0),
        dr.select(finite, 0.0, 1.0),
    ]
    dr.eval(*chans)
    return np.stack([np.array(c, np.float32) for c in chans], -1).reshape(passes, h, w, -1)


def _trace_radiance(scene, path, seed: int, spp: int) -> tuple[np.ndarray, int]:
    """Sum over `spp` samples per pixel of the path integrator's radiance, (H, W, 3) float64,
    and the count of non-finite samples (set to 0). One launch, no AOVs: lanes are pixel-major
    (lane = pixel * spp + k) so the per-pixel sums are a block reduction inside the kernel and
    only W*H*4 floats come back to the host instead of 15 channels per sample."""
    import drjit as dr
    import mitsuba as mi

    sensor = scene.sensors()[0]
    w, h = sensor.film().crop_size()
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(seed, w * h * spp)
    pix = dr.arange(mi.UInt32, w * h * spp) // spp
    film_pos = mi.Vector2f(mi.Float(pix % w), mi.Float(pix // w)) + sampler.next_2d()
    ray, _ = sensor.sample_ray_differential(
        0.0, sampler.next_1d(), film_pos / mi.ScalarVector2f(w, h), sampler.next_2d()
    )
    radiance, _, _ = path.sample(scene, sampler, ray, None, True)
    finite = dr.isfinite(radiance.x) & dr.isfinite(radiance.y) & dr.isfinite(radiance.z)
    chans = [dr.select(finite, c, 0.0) for c in (radiance.x, radiance.y, radiance.z)]
    chans.append(dr.select(finite, 0.0, 1.0))
    dr.eval(*chans)  # one kernel: reducing unevaluated channels one by one re-ran the loop
    sums = [dr.block_sum(c, spp) for c in chans]
    dr.eval(*sums)
    bad = sums.pop()
    img = np.stack([np.array(c, np.float64) for c in sums], -1).reshape(h, w, 3)
    return img, int(np.array(bad).sum())


# Lanes per reference launch: larger launches amortise the per-launch tracing and set-up
# (~0.15 s here); the path-only kernel keeps no per-sample buffers, so memory stays small.
REFERENCE_LANES = 1 << 23


def render_reference(scene, path, seed: int, spp: int) -> tuple[np.ndarray, int]:
    """(H, W, 3) mean of `spp` samples and the count of dropped non-finite samples. JIT
    variants: path-only launches of ~8M samples, summed per pixel on the device (see
    `_trace_radiance`); scalar uses mi.render."""
    import mitsuba as mi

    if mi.variant().startswith("scalar"):
        img = np.array(mi.render(scene, integrator=path, seed=seed, spp=spp), np.float32)[..., :3]
        bad = ~np.isfinite(img).all(-1)
        img[bad] = 0.0
        return img, int(bad.sum())
    w, h = scene.sensors()[0].film().crop_size()
    batch = max(1, REFERENCE_LANES // (w * h))
    total, dropped, done, b = np.zeros((h, w, 3), np.float64), 0, 0, 0
    while done < spp:
        n = min(batch, spp - done)
        img, bad = _trace_radiance(scene, path, _seed(seed, b), n)
        total += img
        dropped += bad
        done, b = done + n, b + 1
    return (total / spp).astype(np.float32), dropped


# ---------------------------------------------------------------------------------------------
# One sequence


def _frame_count(seed: int, cfg: RenderConfig) -> int:
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
                scene, reference, _seed(seed, attempt, 99), preview.PREVIEW_SPP, table)
            rad = np.mean([p["radiance"] for p in passes], 0) @ LUMA
            yield rad, np.where(passes[0]["hit"], passes[0]["depth"], np.inf)

    attempt, lum = preview.first_acceptable(seed, tries, shot_previews)
    desc, scene, reference, table, passes = (
        made[k] for k in ("desc", "scene", "reference", "table", "passes"))
    exposure, clip = preview.exposure(lum, seed)
    # Direct light only (emitters seen directly or after one bounce) on the last previewed
    # shot: the share of the image it explains says whether the scene is lit indirectly.
    direct = mi.load_dict({"type": "path", "max_depth": 2})
    img = np.array(mi.render(scene, integrator=direct, seed=_seed(seed, 98),
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
    n_frames = _frame_count(seed, cfg)
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
    passes = render_passes(scene, reference, _seed(seed, t), cfg.passes, table)
    t_passes = time.perf_counter() - tp
    tr = time.perf_counter()
    ref_dropped = 0
    if shared_ref is None:
        ref, ref_dropped = render_reference(
            scene, reference, _seed(seed, t, 1_000_003), cfg.reference_samples
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


# ---------------------------------------------------------------------------------------------
# Reference noise


# Salt of the second reference `reference_noise` renders (the stored one uses 1_000_003).
REFERENCE_NOISE_SALT = 2_000_003


def _config_of(manifest: dict) -> RenderConfig:
    c = manifest["config"]
    return RenderConfig(
        width=c["width"],
        height=c["height"],
        frames=tuple(c["frames"]),
        spp_levels=tuple(c["spp_levels"]),
        reference_spp=c["reference_spp"],
        max_depth=c["max_depth"],
        locked_off=c.get("locked_off", False),
    )


class SequenceScene:
    """A finished sequence's scene loaded again (one load, then any of its frames): what a
    second reference or extra passes of a stored frame are rendered from. Needs a Mitsuba
    variant set (`set_variant`)."""

    def __init__(self, seq_dir: str | Path) -> None:
        self.dir = Path(seq_dir)
        self.manifest = json.loads((self.dir / MANIFEST).read_text())
        self.config = _config_of(self.manifest)
        desc = self.manifest["scene"]
        self.scene, self.path, self.albedo_table = load_scene(desc, self.config)
        self._cameras = desc["cameras"]
        self._movers = movers_of(self.scene, desc)

    @property
    def seed(self) -> int:
        return self.manifest["seed"]

    @property
    def exposure(self) -> float:
        return self.manifest["exposure"]

    def at(self, frame: int) -> SequenceScene:
        set_frame(self.scene, Camera(**self._cameras[frame]), self._movers, frame)
        return self


def render_second_reference(
    seq_dir: str | Path, frame: int, salt: int = REFERENCE_NOISE_SALT
) -> tuple[np.ndarray, float]:
    """Render another reference of one finished frame, independent of the stored one: the
    sequence's scene, camera and movers at `frame`, as many samples as the stored reference
    (`RenderConfig.reference_samples`) seeded from (sequence seed, frame, `salt`). Returns the
    (H, W, 3) float32 radiance times the sequence's exposure (comparable with the stored
    `reference` layer) and the render's seconds. A salt other than 1_000_003 (the stored
    reference's) and REFERENCE_NOISE_SALT gives a reference independent of both. Needs a
    Mitsuba variant set (`set_variant`)."""
    seq = SequenceScene(seq_dir).at(frame)
    t0 = time.perf_counter()
    second, _ = render_reference(seq.scene, seq.path, _seed(seq.seed, frame, salt),
                                 seq.config.reference_samples)
    seconds = time.perf_counter() - t0
    return (second * seq.exposure).astype(np.float32), seconds


def reference_noise(seq_dir: str | Path, frame: int, eps: float = 0.01) -> dict:
    """Render a second reference of one finished frame with an independent seed and compare
    it with the stored one (luminance, after exposure): the median over pixels of
    |a - b| / ((a + b) / 2 + eps). eps (in units of the exposed image, whose mean is
    0.15-0.6) keeps black pixels from dominating. For independent references of equal spp
    this is ~0.95 x the per-pixel relative standard deviation of one reference (Gaussian)."""
    seq = Path(seq_dir)
    m = json.loads((seq / MANIFEST).read_text())
    second, seconds = render_second_reference(seq, frame)
    stored = exr_io.load_frame(seq / f"frame_{frame:04d}.exr", ["reference"])["reference"]
    a, b = stored @ LUMA, second @ LUMA
    rel = np.abs(a - b) / ((a + b) / 2 + eps)
    return {
        "seed": m["seed"],
        "frame": frame,
        "median_relative_difference": float(np.median(rel)),
        "mean_relative_difference": float(np.mean(rel)),
        "seconds": round(seconds, 1),
    }


# ---------------------------------------------------------------------------------------------
# Colour levels above the stored passes (evaluation at higher spp)

TOPUP_SALT = 4_000_037  # extra passes' seeds: independent of the stored passes and references
TOPUP_KEY = "topup_spp_levels"


def topup_sequence(seq_dir: str | Path, spp: int) -> int:
    """Add a colour level of `spp` samples (more than the stored passes, e.g. 16 over 8) to
    every frame of a finished sequence: spp − passes further one-sample passes, seeded from
    (sequence seed, frame, TOPUP_SALT), averaged with the stored passes into `color_<spp>spp`.
    The aux buffers and motion stay those of the stored passes (means over 8 samples: nearly
    noise-free already). Frames that have the level are skipped; the level is listed under
    `topup_spp_levels` in the manifest and the frames' metadata, not in `config.spp_levels`,
    so the render config (and resuming `render`) is unchanged and training never draws it.
    Returns the number of frames written."""
    seq_dir = Path(seq_dir)
    manifest = json.loads((seq_dir / MANIFEST).read_text())
    stored = max(manifest["config"]["spp_levels"])
    if spp <= stored:
        raise ValueError(f"{seq_dir}: {spp} spp is stored already (passes: {stored})")
    layer = exr_io.color_layer(spp)
    todo = [f for f in sorted(seq_dir.glob("frame_*.exr")) if layer not in exr_io.frame_layers(f)]
    seq = SequenceScene(seq_dir) if todo else None
    for path in todo:
        meta = exr_io.read_meta(path)
        frame = int(meta["frame"])
        layers = exr_io.load_frame(path)
        extra = render_passes(seq.at(frame).scene, seq.path, _seed(seq.seed, frame, TOPUP_SALT),
                              spp - stored, seq.albedo_table)
        total = layers[exr_io.color_layer(stored)].astype(np.float64) * stored
        total += np.sum([p["radiance"] for p in extra], 0, dtype=np.float64) * seq.exposure
        layers[layer] = (total / spp).astype(np.float32)
        meta[TOPUP_KEY] = sorted({*meta.get(TOPUP_KEY, []), spp})
        exr_io.write_frame(path, layers, meta)
    if todo or spp not in manifest.get(TOPUP_KEY, []):
        manifest[TOPUP_KEY] = sorted({*manifest.get(TOPUP_KEY, []), spp})
        write_json(seq_dir / MANIFEST, manifest)
    return len(todo)
