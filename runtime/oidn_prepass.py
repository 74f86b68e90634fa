"""A per-frame Open Image Denoise pass that runs before a model's graph (the oidn-temporal tier).

A model's card lists it as an OIDN stage (runtime/card.py); files written before the card say
it in their metadata (docs/model-interface.md):

    quietframe.prepass = {"oidn": {"quality": "high", "prefilter_aux": false}, "input": "oidn",
                          "color_from": "accumulation.onnx"}

and the runtime (`Denoiser`) runs OIDN's RT filter on the frame's sanitised color, albedo and
normal and feeds the result to the graph input named by "input". With "color_from" (optional),
OIDN denoises the output of that model (a file in the composed model's folder, run with its own
state, e.g. the reprojected accumulation of the noisy colour) instead of the frame's colour: it
then sees several frames' samples instead of one. A `prefilter_aux` stage can also run in two
calls: its aux filters alone (`prefilter`, on a frame or any crop of one), then its colour filter
on those aux (`clean_aux=True`), equal to the one call (experiments/aux_history.py uses the split
to give the colour filter aux prefiltered for an earlier frame). pyoidn is optional: without it
`OIDNPrepass` raises `PrepassUnavailable`, and the service leaves such models out.

Resources: a sequence's frames run through one `OIDNFilters` (runtime/stream.py owns it): its
own OIDN device and the committed filters of its frame size, kept between frames. Rebuilding
them per frame cost ~14% of OIDN's CPU time at 720p (a new filter's first execution allocates and
touches its scratch afresh). A kept RT filter holds its scratch (up to `maxMemoryMB`) until it is
released, so the owner counts what it keeps (`working_set_bytes`) and releases it when told
(`OIDNFilters.release`: the service does so when the history budget needs the room, or the
session ends). A call without filters (a single frame, a tool) builds them for that call on the
calling thread's device and releases them after it. OIDN serialises the calls on one device, so
one sequence's frames may run on any worker thread, one at a time. Memory: OIDN tiles large
images itself (its own alignment and overlap) to fit its `maxMemoryMB`, which the runtime sets
from its one memory bound (`scratch_bytes`). pyoidn binds numpy memory zero-copy without keeping it
alive: every bound array is held by the filter set that binds it, frames are copied into those
arrays, and filters are released before their arrays.

Row order: OIDN's network is not flip-equivariant, so the same frame denoised top-down and
bottom-up differs (up to ~0.3 dB a shot). Cycles hands OIDN its buffers bottom-up (Blender's
images start at the bottom row); EXRs and the service's planes are top-down. For a frame whose
renderer denoises bottom-up (`BOTTOM_UP_RENDERERS`), the stage gives OIDN the rows in that
order, so its per-frame output is the renderer's own denoise (Blender's `Combined` to the
half-float rounding of the stored file: experiments/blender_denoise_match.py), the baseline a farm
compares with; every other frame keeps the stored order.
"""

from __future__ import annotations

import threading
from collections.abc import Iterable, Mapping

import numpy as np

from quietframe.runtime.card import PREFIX, OIDNStage, parse_prepass

QUALITIES = {"fast": "OIDN_QUALITY_FAST", "balanced": "OIDN_QUALITY_BALANCED",
             "high": "OIDN_QUALITY_HIGH"}
PREPASS_KEY = PREFIX + "prepass"
PREPASS_BUFFERS = ("color", "albedo", "normal")  # what OIDN reads, as (3, H, W) planes
OIDN_DEFAULT_MAX_MEMORY_MB = 3000  # OIDN 2's CPU default for maxMemoryMB
# OIDN 2.5's scratch for one RT filter on the CPU, bytes a pixel, when it does not tile: RSS
# growth over the first execution, 552-573 B/px at high and balanced quality and 306-309 at
# fast, from 640x360 to 2560x1440 (numThreads 2); rounded up. Below maxMemoryMB it holds this.
SCRATCH_BYTES_PER_PIXEL = {"high": 600, "balanced": 600, "fast": 340}
# At high quality with clean aux (and an aux filter at high) OIDN runs its large network:
# 680-687 B/px at 720p and 1080p, and ~2.4x the CPU of high with noisy aux.
LARGE_SCRATCH_BYTES_PER_PIXEL = 700
BOTTOM_UP_RENDERERS = frozenset({"cycles"})  # renderers whose own OIDN call sees rows bottom-up

OIDNSettings = OIDNStage  # the prepass settings are the card's OIDN stage (runtime/card.py)


class PrepassUnavailable(RuntimeError):
    """The model needs a prepass this installation cannot run (pyoidn is not installed)."""

    model: str | None = None  # the model's name, set by the runtime that loads it


def read_prepass(metadata: Mapping[str, str]) -> OIDNSettings | None:
    """The model's prepass from its metadata (with `color_from` as written), or None."""
    return parse_prepass(metadata.get(PREPASS_KEY))


def import_pyoidn():
    """pyoidn, or PrepassUnavailable saying how to get it."""
    try:
        import pyoidn
    except ImportError as exc:
        raise PrepassUnavailable(
            "this model runs Open Image Denoise first and needs the pyoidn package "
            "(pip install 'quietframe[oidn]')") from exc
    return pyoidn


def rows_bottom_up(renderer: str | None) -> bool:
    """Whether OIDN is given a frame of `renderer` bottom-up, as that renderer's own denoise
    gives it (module docstring); None (unknown) keeps the stored top-down order."""
    return renderer in BOTTOM_UP_RENDERERS


def usable_aux(wanted: tuple[str, ...], present: Iterable[str]) -> tuple[str, ...]:
    """The aux images OIDN gets for a frame: those wanted that the frame has, a normal only
    together with an albedo (OIDN's rule)."""
    have = set(present)
    if "albedo" not in have:
        return ()
    return tuple(name for name in wanted if name in have)


class _FilterSet:
    """Committed RT filters for one image size and aux set on one device, with the arrays they
    bind. `prefilters`: the aux filters of a `prefilter_aux` stage run first (False: the aux
    given are already clean: prefiltered for an earlier frame); `main`: the colour filter (False:
    the aux filters alone, their outputs under `clean_<name>`)."""

    def __init__(self, pyoidn, device, settings: OIDNSettings, shape: tuple[int, int],
                 aux: tuple[str, ...], max_memory_mb: float | None = None,
                 prefilters: bool = True, main: bool = True) -> None:
        self._oidn, self._device = pyoidn, device
        self._max_memory_mb = max_memory_mb
        prefilters = prefilters and settings.prefilter_aux
        self.inputs = ("color", *aux) if main else aux
        names = [*self.inputs, *(("output",) if main else ())]
        if prefilters:
            names += [f"clean_{name}" for name in aux]
        # (H, W, 3) interleaved: OIDN's FLOAT3 layout; the runtime's planes are copied in.
        self.bound = {k: np.zeros((*shape, 3), np.float32) for k in names}
        self.filters: list = []  # execution order: [albedo, normal,] main
        images = {name: name for name in aux}
        if prefilters:
            for name in aux:
                self._add({name: name, "output": f"clean_{name}"}, settings,
                          settings.aux_quality or settings.quality)
            images = {name: f"clean_{name}" for name in aux}
        if main:
            self._add({"color": "color", **images, "output": "output"}, settings,
                      settings.quality)

    def _add(self, images: dict[str, str], settings: OIDNSettings, quality: str) -> None:
        oidn = self._oidn
        flt = oidn.Filter(self._device, oidn.OIDN_FILTER_TYPE_RT)
        self.filters.append(flt)  # released by close() even if configuring fails
        for slot, key in images.items():
            flt.set_image(slot, self.bound[key], oidn.OIDN_FORMAT_FLOAT3)
        flt.set_quality(getattr(oidn, QUALITIES[quality]))
        if self._max_memory_mb:  # OIDN tiles the image itself to fit (its own overlap)
            flt.set_int("maxMemoryMB", int(self._max_memory_mb))
        if "color" in images:
            flt.set_bool("hdr", True)
            flt.set_bool("cleanAux", settings.prefilter_aux)
        flt.commit()
        _check(self._device, "filter commit")

    def run(self, planes: Mapping[str, np.ndarray], bottom_up: bool = False,
            outputs: tuple[str, ...] = ("output",)) -> dict[str, np.ndarray]:
        """Run the filters on (3, H, W) `planes`; the named bound outputs as (3, H, W) copies."""
        rows = slice(None, None, -1) if bottom_up else slice(None)  # the copies reorder rows
        for name in self.inputs:  # (3, H, W) -> (H, W, 3)
            np.copyto(self.bound[name], planes[name][:, rows].transpose(1, 2, 0))
        for flt in self.filters:
            flt.execute()
            _check(self._device, "execute")
        return {name: np.ascontiguousarray(self.bound[name][rows].transpose(2, 0, 1))
                for name in outputs}

    def close(self) -> None:
        for flt in self.filters:  # filters first, then (by dropping them) the bound arrays
            flt.release()
        self.filters, self.bound = [], {}


def _check(device, what: str) -> None:
    error = device.get_error()
    if error is not None:
        raise RuntimeError(f"OIDN prepass: {what} failed: {error}")


class _ThreadDevice:
    """One worker thread's OIDN device."""

    def __init__(self, pyoidn, num_threads: int) -> None:
        self.device = pyoidn.Device(pyoidn.OIDN_DEVICE_TYPE_CPU)
        if num_threads:
            self.device.set_int("numThreads", num_threads)
        self.device.commit()
        _check(self.device, "device creation")

    def close(self) -> None:
        self.device.release()


class OIDNPrepass:
    """OIDN's RT filter on (3, H, W) planes; thread-safe (per-thread device and filters)."""

    def __init__(self, settings: OIDNSettings, num_threads: int = 0,
                 max_memory_mb: float | None = None) -> None:
        self._oidn = import_pyoidn()
        self.settings, self.num_threads = settings, num_threads  # 0: all cores (OIDN default)
        self.max_memory_mb = max_memory_mb  # OIDN's maxMemoryMB; None: OIDN's default
        self._local = threading.local()
        self._lock = threading.Lock()
        self._all: list[_ThreadDevice] = []  # every thread's, for close()
        self.devices_created = 0  # counters for tests and logs
        self.filter_sets_built = 0

    def _device(self) -> _ThreadDevice:
        device = getattr(self._local, "device", None)
        if device is None:
            device = _ThreadDevice(self._oidn, self.num_threads)
            self._local.device = device
            with self._lock:
                self._all.append(device)
                self.devices_created += 1
        return device

    def working_set_bytes(self, height: int, width: int) -> int:
        """What one frame's filters hold while they run (and an `OIDNFilters` keeps between
        frames): the bound (H, W, 3) float32 arrays (colour, aux, output, prefiltered aux) and
        OIDN's scratch: what the frame needs untiled, or maxMemoryMB where OIDN tiles to fit
        (the filters of one device share it)."""
        aux = len(self.settings.aux)
        arrays = 2 + aux + (aux if self.settings.prefilter_aux else 0)
        return arrays * 12 * height * width + self.scratch_bytes(height, width)

    def scratch_bytes(self, height: int, width: int) -> int:
        """OIDN's scratch for an H×W frame: its untiled need, capped by maxMemoryMB."""
        cap = self.max_memory_mb if self.max_memory_mb else OIDN_DEFAULT_MAX_MEMORY_MB
        settings = self.settings
        qualities = {settings.quality, settings.aux_quality or settings.quality}
        per_pixel = max(SCRATCH_BYTES_PER_PIXEL[q] for q in qualities)
        if settings.prefilter_aux and "high" in qualities:
            per_pixel = LARGE_SCRATCH_BYTES_PER_PIXEL
        need = per_pixel * height * width
        return min(need, int(cap * 2**20))

    def filters(self) -> OIDNFilters:
        """A sequence's own filters (runtime/stream.py): kept between its frames."""
        return OIDNFilters(self)

    def __call__(self, planes: Mapping[str, np.ndarray], renderer: str | None = None,
                 clean_aux: bool = False, filters: OIDNFilters | None = None) -> np.ndarray:
        """OIDN's output (1, 3, H, W) float32 for sanitised (3, H, W) planes: the colour, and
        the settings' aux images the frame has (absent ones are not given to OIDN: it filters
        the colour alone, or with the albedo alone, rather than read zeros as a black albedo).
        `renderer` (the frame's, where known) sets the row order OIDN sees (rows_bottom_up).
        `clean_aux`: the aux planes are already prefiltered (`prefilter`), so the stage's aux
        filters do not run again. `filters`: a sequence's kept filters (else built for this
        call)."""
        _, height, width = planes["color"].shape
        aux = usable_aux(self.settings.aux, planes)
        out = self._run(planes, (height, width), aux, renderer, ("output",), filters,
                        prefilters=not clean_aux)
        return out["output"][None]

    def prefilter(self, planes: Mapping[str, np.ndarray], renderer: str | None = None,
                  filters: OIDNFilters | None = None) -> dict[str, np.ndarray]:
        """The stage's aux filters alone on (3, H, W) aux planes (any size: a crop of a frame
        too): {name: prefiltered (3, H, W)} for the settings' aux the planes hold."""
        aux = usable_aux(self.settings.aux, planes)
        if not self.settings.prefilter_aux or not aux:
            raise ValueError("prefilter: the stage prefilters no aux (prefilter_aux off) or the "
                             "planes hold no albedo; give an albedo, and a normal if wanted")
        _, height, width = planes[aux[0]].shape
        out = self._run(planes, (height, width), aux, renderer,
                        tuple(f"clean_{name}" for name in aux), filters, main=False)
        return {name: out[f"clean_{name}"] for name in aux}

    def _run(self, planes: Mapping[str, np.ndarray], shape: tuple[int, int],
             aux: tuple[str, ...], renderer: str | None, outputs: tuple[str, ...],
             filters: OIDNFilters | None, **roles: bool) -> dict[str, np.ndarray]:
        if filters is not None:
            return filters.get(shape, aux, **roles).run(planes, rows_bottom_up(renderer), outputs)
        filter_set = self.build(self._device().device, shape, aux, **roles)
        try:
            return filter_set.run(planes, rows_bottom_up(renderer), outputs)
        finally:
            filter_set.close()  # its scratch and bound arrays go with it (module docstring)

    def build(self, device, shape: tuple[int, int], aux: tuple[str, ...],
              **roles: bool) -> _FilterSet:
        """Committed filters for `shape` and `aux` on `device` (counted for tests and logs)."""
        filter_set = _FilterSet(self._oidn, device, self.settings, shape, aux,
                                self.max_memory_mb, **roles)
        with self._lock:
            self.filter_sets_built += 1
        return filter_set

    def close(self) -> None:
        """Release every thread's device (no thread may be running a frame)."""
        with self._lock:
            for device in self._all:
                device.close()
            self._all.clear()
        self._local = threading.local()


class OIDNFilters:
    """One sequence's OIDN filters, kept between its frames: its own device (OIDN serialises the
    calls on a device, so the frames may run on any thread, one at a time) and the committed
    filter sets of its current frame size, one per aux set and role. A frame of another size
    releases the kept ones first, so it holds at most one size's (`working_set_bytes`)."""

    def __init__(self, prepass: OIDNPrepass) -> None:
        self.prepass = prepass
        self._device: _ThreadDevice | None = None
        self._sets: dict[tuple, _FilterSet] = {}
        self.shape: tuple[int, int] | None = None

    def get(self, shape: tuple[int, int], aux: tuple[str, ...], **roles: bool) -> _FilterSet:
        if shape != self.shape:
            self.release()
            self.shape = shape
        key = (aux, tuple(sorted(roles.items())))
        filter_set = self._sets.get(key)
        if filter_set is None:
            if self._device is None:
                self._device = _ThreadDevice(self.prepass._oidn, self.prepass.num_threads)
                with self.prepass._lock:
                    self.prepass.devices_created += 1
            filter_set = self.prepass.build(self._device.device, shape, aux, **roles)
            self._sets[key] = filter_set
        return filter_set

    @property
    def kept_bytes(self) -> int:
        """What the kept filters hold (0 after `release`)."""
        if self.shape is None or not self._sets:
            return 0
        return self.prepass.working_set_bytes(*self.shape)

    def release(self) -> None:
        """Release the kept filters (their scratch and arrays); the device stays for the next
        frame. Nothing of this sequence may be running."""
        for filter_set in self._sets.values():
            filter_set.close()
        self._sets.clear()
        self.shape = None

    def close(self) -> None:
        self.release()
        if self._device is not None:
            self._device.close()
            self._device = None
