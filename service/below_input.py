"""The warning for a model asked for by name (not `auto`) at an spp where its card says it made a
validation-zoo shot worse than its own noisy input (`input_margin`, runtime/card.py). `auto`
leaves such a model out there (choice_policy.not_below_input); a session that names it is
served as asked, and its replies say so in X-Quietframe-Warning: on each frame at such an spp
(service/frame_path.py), and on the session's creation where its `spp` option is one
(service/routers/sessions.py). One place for the text, ASCII as a header value must be."""

from __future__ import annotations

from quietframe.client.session_fields import AUTO
from quietframe.runtime import Denoiser
from quietframe.runtime.card import SAMPLES_INPUT
from quietframe.service.model_profiles import profile_of
from quietframe.service.model_registry import ModelRegistry
from quietframe.service.session import Session

FRAME = "this frame"
SESSION_OPTION = f"the session's model_options.{SAMPLES_INPUT}"


def below_input_warning(name: str, denoiser: Denoiser, spp: float | None,
                        renderer: str | None, where: str = FRAME) -> str | None:
    """The warning for model `name` given frames at `spp` (`where` says whose spp it is), read
    from its table for `renderer` as `auto` reads it (ModelProfile.input_margin below 0); None
    where the spp is unknown, the card has no `input_margin` or the model is not below there."""
    if spp is None:
        return None
    profile = profile_of(name, denoiser, renderer)
    margin, start = profile.input_margin(spp), profile.worse_than_input_from()
    if margin is None or margin >= 0 or start is None:
        return None
    return header_text(
        f"{name} is below its own noisy input from {start:g} spp on a validation-zoo shot "
        f"({where}: {spp:g} spp, {margin:+.2f} dB there); use model=auto or an OIDN tier")


def creation_warning(session: Session, models: ModelRegistry) -> str | None:
    """The warning for a session created with a model's name and an `spp` option in its range
    (the frames' renderer is not known yet: the default renderer's table, as GET /v1/models
    shows it); None for `auto` and where the session states no spp."""
    spec = session.spec
    if spec.model == AUTO:
        return None
    spp = spec.model_options.get(SAMPLES_INPUT)
    name = session.info.name
    return below_input_warning(name, models.denoiser(name),
                               None if spp is None else float(spp), None, SESSION_OPTION)


def header_text(text: str) -> str:
    """`text` as an HTTP header value: printable ASCII, anything else (a model's file name in
    another script, a control character) as `?`."""
    return "".join(c if " " <= c <= "~" else "?" for c in text)
