"""How a `quietframe` run ends: the exit codes a farm scheduler acts on, and for each failure the
one piece of advice that applies (resume only where resuming helps; CLI flags, not API words).

| code | meaning | what the farm should do |
|---|---|---|
| 0 | done (warnings, if any, in the summary) | - |
| 1 | an unexpected failure (a bug: report it) | fail the task |
| 2 | configuration: flags, URL, token, model, channel mapping, changed flags | fix the job |
| 3 | input: unreadable/truncated frames, size changes, missing passes, files in the way | fix it |
| 75 | server unavailable or busy (EX_TEMPFAIL): connection, timeouts, 5xx, 429 | requeue |
| 130 / 143 | interrupted by SIGINT (Ctrl-C) / SIGTERM; rerun to resume | requeue |
"""

from __future__ import annotations

import re
from dataclasses import dataclass

OK, FAILURE, CONFIG, INPUT, UNAVAILABLE = 0, 1, 2, 3, 75
INTERRUPTED = {"SIGINT": 130, "SIGTERM": 143}

# Server error codes by whose fix they need. `missing_channels` / `ambiguous_channels` are a
# configuration error when the run passed a mapping (--channels / --layer), else an input one.
_CONFIG_CODES = frozenset({
    "unauthorized", "unknown_model", "model_unavailable", "invalid_model_options",
    "invalid_request", "not_found", "method_not_allowed", "resolution_too_large",
})
_MAPPING_CODES = frozenset({"missing_channels", "ambiguous_channels"})
_INPUT_CODES = frozenset({"bad_exr", "unsupported_exr", "size_mismatch", "body_too_large",
                          "unsupported_media_type"})
_RETRYABLE_STATUS = frozenset({0, 408, 429, 500, 502, 503, 504})

# API words in the server's messages, and what a CLI user types instead.
_CLI_WORDS = (
    (re.compile(r" when creating the session"), ""),
    (re.compile(r"the session's channel mapping \(`channels`, CLI --channels "), "--channels ("),
    (re.compile(r"a channel mapping \(`channels`, "), "--channels ("),
    (re.compile(r"(a |the )?(session's )?(session|channel) mapping"), "--channels"),
    (re.compile(r"\(session model\)"), "(--model)"),
    (re.compile(r"GET /v1/models"), "`quietframe models`"),
    (re.compile(r"\bmodel_options\b"), "--model-option"),
    (re.compile(r"\bmotion_scale\b"), "--motion-scale"),
    (re.compile(r"\bdenoised_layer\b"), "--denoised-layer"),
)


@dataclass(frozen=True)
class Failure:
    code: int  # the exit code
    message: str  # what went wrong, in CLI words
    advice: str  # the one fix that applies


def cli_words(text: str) -> str:
    for pattern, words in _CLI_WORDS:
        text = pattern.sub(words, text)
    return text


def server_failure(status: int, code: str, detail: str, server: str, mapping: bool,
                   layers: tuple[str, ...] = ()) -> Failure:
    """A request that failed for good (client.QuietframeError's fields). `mapping`: the run
    passed --channels or --layer; `layers`: view layers of the first frame (for --layer)."""
    detail = cli_words(detail)
    if status in _RETRYABLE_STATUS and code != "not_found":
        what = (f"cannot reach the quietframe server at {server} ({detail})" if status == 0
                else f"the server at {server} answered {status} {code}: {detail}")
        return Failure(UNAVAILABLE, what,
                       "run the same command again when the server is up; finished frames are "
                       "kept and the run resumes")
    message = f"{status} {code}: {detail}"
    if code in _MAPPING_CODES:
        if len(layers) > 1 and not mapping:
            return Failure(INPUT, message,
                           f"the frames hold several view layers ({', '.join(layers)}): pass "
                           "--layer NAME, or --layer all for every one")
        if mapping:
            return Failure(CONFIG, message, "fix --channels / --layer for these frames")
        return Failure(INPUT, message, "render the passes named above, or map them with "
                       "--channels (`quietframe models` lists what each model needs)")
    if code == "not_found":
        return Failure(CONFIG, message, f"check --server: {server} does not serve the quietframe "
                       "API (give the root URL, e.g. http://denoise:8000)")
    if code == "unauthorized":
        return Failure(CONFIG, message, "pass the server's token with --token or "
                       "QUIETFRAME_TOKEN")
    if code in ("unknown_model", "model_unavailable", "invalid_model_options"):
        return Failure(CONFIG, message, f"`quietframe models --server {server}` lists the "
                       "installed models and their options")
    if code in _CONFIG_CODES:
        return Failure(CONFIG, message, "fix the flags named above")
    if code in _INPUT_CODES:
        return Failure(INPUT, message, "fix or re-render that frame, then run the same command "
                       "again to resume")
    return Failure(FAILURE, message, "run the same command again to resume; if it fails the "
                   "same way, report it with the server log")
