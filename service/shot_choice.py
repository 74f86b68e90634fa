"""`model=auto` for a shot, as a session makes it: at the shot's first frame (a session's first
frame, a cut) the frame is decoded, its noise measured and a model chosen (service/choice_policy.py)
or, where the shot's model was chosen before (`shot_model`: another farm chunk of the shot), kept;
and how the choice is said (X-Quietframe-Choice, the choices metric)."""

from __future__ import annotations

from quietframe.service.choice_policy import Choice, choose
from quietframe.service.frame_context import FrameContext
from quietframe.service.frame_evidence import SESSION_SAMPLES
from quietframe.service.model_profiles import ModelProfile
from quietframe.service.model_registry import ModelRegistry
from quietframe.service.noise_estimate import ESTIMATE, NoiseLevel, estimate_spp, shot_samples
from quietframe.service.session_spec import SessionSpec
from quietframe.wire.protocol import Reset

# A choice is revisited only where the history starts afresh for a new shot anyway: switching
# models inside a shot would change its look from one frame to the next (flicker). A gap keeps
# the shot's model (it is a skipped frame more often than a new shot).
CHOICE_RESETS = (Reset.FIRST_FRAME, Reset.CUT)

# The reason of a shot's model kept from an earlier choice (`shot_model`, e.g. another farm
# chunk's): the choice is made once per shot, so chunks of one shot never switch models.
KEPT_REASON = "kept: the shot's model, chosen before for this shot (shot_model)"

# The non-ASCII symbols the choice's reason uses, as the header spells them.
HEADER_WORDS = {"σ": "sigma", "×": "x", "≤": "<=", "≥": ">=", "–": "-", "—": "-", "·": "*"}


def choose_for_shot(context: FrameContext, body: bytes | bytearray, spec: SessionSpec,
                    models: ModelRegistry, keep: str | None) -> tuple[FrameContext, Choice]:
    """(the frame decoded, the shot's model) on the worker pool: the spp the session or the
    header states, else estimated from the decoded colour (and albedo), which also measures how
    noisy the frame looks (noise_estimate.noise_statistic); the tables of the frame's renderer.
    `keep`: the model already chosen for this shot, described with what the frame shows."""
    context = context.decode(body)
    assert context.decoded is not None
    planes = context.decoded.buffers
    noise = estimate_spp(planes["color"], planes.get("albedo"), models.calibration,
                         header=context.stated)
    profiles = models.profiles_for(context.renderer)
    pixels = spec.width * spec.height
    if keep is not None:
        return context, kept_choice(keep, context.present, noise, profiles, pixels)
    return context, choose(
        context.present,
        noise,
        profiles,
        models.default,
        quality=spec.quality,
        latency_ms=spec.latency_ms,
        pixels=pixels,
    )


def estimate_for_shot(context: FrameContext, body: bytes | bytearray,
                      models: ModelRegistry) -> tuple[FrameContext, float | None]:
    """(the frame decoded, its estimated spp) on the worker pool, for a session that names a
    model reading the frame's spp where neither its options nor the header state one
    (Stream.wants_estimate), at the shot's first frame as `auto` measures it; the shot's
    frames then share it (Session.shot_spp). None where nothing is measurable
    (noise_estimate.shot_samples): the model's default, and the next frame estimates again."""
    context = context.decode(body)
    assert context.decoded is not None
    planes = context.decoded.buffers
    return context, shot_samples(planes["color"], planes.get("albedo"), models.calibration)


def kept_choice(name: str, present: list[str], noise: NoiseLevel,
                profiles: list[ModelProfile], pixels: int) -> Choice:
    """A shot's choice made earlier, as the session reports it: that model, with what this
    frame carries and how noisy it is, and what the model's table expects there."""
    have = tuple(sorted(set(present)))
    profile = next((p for p in profiles if p.name == name), None)
    psnr = ms = None
    if profile is not None and profile.measured:
        by_noise = noise if profile.psnr_by_noise else None
        psnr = round(profile.expected_psnr(noise.spp, have, by_noise), 2)
        ms = round(profile.expected_ms(pixels), 3)
    sigma = None if noise.log2_sigma is None else round(noise.log2_sigma, 3)
    return Choice(name, KEPT_REASON, noise.spp, noise.source, have, sigma, psnr, ms)


def choice_header(choice: Choice) -> str:
    spp = "unknown" if choice.spp is None else f"{choice.spp:g}"
    text = f"{choice.model}; spp={spp}; source={choice.noise_source}; reason={choice.reason}"
    for symbol, word in HEADER_WORDS.items():  # spelled out, not turned into "?"
        text = text.replace(symbol, word)
    return text.encode("ascii", "replace").decode()  # an HTTP header value is latin-1


def noise_kind(choice: Choice) -> str:
    """Where the choice's spp came from, as the choices metric counts it: a header attribute
    is `header`, the session's model_options `session`, else `estimate` or `unknown`."""
    if choice.noise_source == SESSION_SAMPLES:
        return "session"
    return choice.noise_source if choice.noise_source in (ESTIMATE, "unknown") else "header"
