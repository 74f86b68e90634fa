"""Tracing a loaded Mitsuba scene (`render.load_scene`): one-sample passes with their AOVs and
reference renders, on the JIT variants as single wavefront launches, on the scalar one (CI)
through `mi.render`. Every launch is seeded from integers (`sampler_seed`), so a frame renders
the same on any machine.
"""

from __future__ import annotations

import numpy as np


def sampler_seed(*parts: int) -> int:
    """A 31-bit Mitsuba sampler seed from a tuple of ints (stable across runs and machines)."""
    return int(np.random.SeedSequence(list(parts)).generate_state(1)[0] & 0x7FFFFFFF)


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
            np.array(mi.render(scene, seed=sampler_seed(seed, k), spp=1), np.float32)
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
        img, bad = _trace_radiance(scene, path, sampler_seed(seed, b), n)
        total += img
        dropped += bad
        done, b = done + n, b + 1
    return (total / spp).astype(np.float32), dropped
