"""Pre-flight of a sequence before the first upload: every frame's header and chunk table (no
pixels), so a size change, a truncated file, a missing pass or a gap is reported at once, for
the whole shot, instead of when its frame is reached.

The server's alias table (which channels are colour, albedo, ...) stays on the server; here
every frame is compared with the first one: the same size, view layers and channel names.

`--dry-run` adds what the server would refuse before the first frame is denoised, read from its
model listing (GET /v1/models) and the first frame's header: an unknown model or option,
view layers that need `--layer`, a `--channels` entry naming no channel of the file. Each is
said as the run says it (outcome.server_failure with the server's own words), so a dry run and
the run end with the same exit code and advice. The session's settings themselves the server
judges: the dry run opens the session the run would open and deletes it (cli._dry_run).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import OpenEXR

from quietframe.client.exr_check import incomplete
from quietframe.client.outcome import Failure, server_failure
from quietframe.wire.protocol import view_layers


@dataclass(frozen=True)
class FrameHeader:
    size: tuple[int, int]
    channels: frozenset[str]
    layers: tuple[str, ...]


@dataclass
class Report:
    frames: int
    size: tuple[int, int] | None = None
    layers: tuple[str, ...] = ()
    channels: int = 0
    names: tuple[str, ...] = ()  # the first frame's channel names, sorted
    errors: list[str] = field(default_factory=list)  # each stops the run
    warnings: list[str] = field(default_factory=list)  # said in the summary

    @property
    def ok(self) -> bool:
        return not self.errors


def read_header(path: Path) -> FrameHeader:
    """ValueError with the reason when the header cannot be read."""
    try:
        parts = OpenEXR.File(str(path), header_only=True).parts
    except Exception as exc:
        raise ValueError(f"not a readable EXR file ({exc})") from exc
    low, high = parts[0].header["dataWindow"]
    names = frozenset(c.name for part in parts for c in part.header["channels"])
    size = (int(high[0] - low[0] + 1), int(high[1] - low[1] + 1))
    return FrameHeader(size, names, view_layers(names))


def check_frames(files: list[Path], missing: tuple[int, ...] = (), limit: int = 10,
                 pre_roll_missing: tuple[int, ...] = (),
                 post_roll_missing: tuple[int, ...] = ()) -> Report:
    """Every file against the first; `missing`: frame numbers of the range without a file
    (a gap: warned); `pre_roll_missing`: those of the pre-roll (warned: the chunk starts on a
    short history); `post_roll_missing`: those of the post-roll (warned: its last frames get a
    shorter look-ahead). At most `limit` errors are listed, then a count."""
    report = Report(len(files))
    first: FrameHeader | None = None
    problems: list[str] = []
    for path in files:
        try:
            header = read_header(path)
        except ValueError as exc:
            problems.append(f"{path.name}: {exc}")
            continue
        if first is None:
            first = header
        problems += [f"{path.name}: {p}" for p in _differences(first, header)]
        cut_short = incomplete(path)
        if cut_short:
            problems.append(f"{path.name}: {cut_short}")
    if first is not None:
        report.size, report.layers, report.channels = first.size, first.layers, len(first.channels)
        report.names = tuple(sorted(first.channels))
    report.errors = problems[:limit]
    if len(problems) > limit:
        report.errors.append(f"... and {len(problems) - limit} more")
    if missing:
        report.warnings.append(f"missing frame(s) {format_numbers(missing)}: the history starts "
                               "afresh after each gap (as at a camera cut)")
    if pre_roll_missing:
        report.warnings.append(
            f"missing pre-roll frame(s) {format_numbers(pre_roll_missing)}: the chunk starts on "
            "a shorter history (a visible pop at its first frame); its outputs are recorded as "
            "such, and a rerun once those frames are rendered redoes them (a shot's first "
            "chunk: pass --cut at its first frame, or --pre-roll 0)")
    if post_roll_missing:
        report.warnings.append(
            f"missing post-roll frame(s) {format_numbers(post_roll_missing)}: the chunk's last "
            "frames look ahead to fewer frames; their outputs are recorded as such, and a rerun "
            "once those frames are rendered redoes them (a shot's last chunk: pass --cut at the "
            "frame after its last, or --post-roll 0)")
    return report


def _differences(first: FrameHeader, header: FrameHeader) -> list[str]:
    found = []
    if header.size != first.size:
        found.append(f"is {header.size[0]}x{header.size[1]}, the first frame "
                     f"{first.size[0]}x{first.size[1]} (denoise sizes as separate sequences)")
    if header.layers != first.layers:
        found.append(f"view layers {list(header.layers)}, the first frame's {list(first.layers)}")
    lacking = sorted(first.channels - header.channels)
    if lacking:
        shown = ", ".join(lacking[:6]) + (" ..." if len(lacking) > 6 else "")
        found.append(f"lacks {len(lacking)} channel(s) the first frame has: {shown}")
    return found


def format_numbers(numbers: tuple[int, ...] | list[int]) -> str:
    """1001-1003, 1007 (runs of consecutive numbers joined)."""
    runs: list[list[int]] = []
    for n in sorted(numbers):
        if runs and n == runs[-1][-1] + 1:
            runs[-1].append(n)
        else:
            runs.append([n])
    return ", ".join(f"{r[0]}-{r[-1]}" if len(r) > 1 else str(r[0]) for r in runs)


AUTO = "auto"


def model_names(listing: dict) -> list[str]:
    """Installed model names of a GET /v1/models reply, sorted as the server lists them."""
    return sorted(m["name"] for m in listing.get("models") or ())


def check_model(listing: dict, model: str, options: dict, server: str) -> Failure | None:
    """The server's refusal of a session for `model` and `options` (--model-option), judged
    from its listing: the model a name or file stem it has, each option one the model (for auto:
    some model) declares, with a value it takes. None when the session would be made."""
    models = {m["name"]: m for m in listing.get("models") or ()}
    stems = {Path(m.get("file") or "").stem: name for name, m in models.items()}
    if model != AUTO and model not in models and model not in stems:
        return server_failure(422, "unknown_model", f"unknown model {model!r}; installed: "
                              f"{model_names(listing)} or 'auto'", server, False)
    chosen = models.get(model) or models.get(stems.get(model, ""))
    problem = _option_problem(models, chosen, options)
    if problem is None:
        return None
    hints = "; ".join([*_option_hints(models, chosen, options),
                       "GET /v1/models lists each model's options and allowed values"])
    return server_failure(422, "invalid_model_options", f"model_options: {problem}; {hints}",
                          server, False)


def _option_hints(models: dict[str, dict], chosen: dict | None, options: dict) -> list[str]:
    """Which models have the refused options (the server's hint, in its order)."""
    declared: dict[str, list[str]] = {}
    for name, m in models.items():
        for option in m.get("options") or ():
            declared.setdefault(option["name"], []).append(name)
    if not declared:
        return ["no installed model takes run-time options: leave model_options out"]
    own = set(declared) if chosen is None else {o["name"] for o in chosen.get("options") or ()}
    hints = [f"models with {name}: {', '.join(declared[name])}"
             for name in sorted(options) if name in declared and name not in own]
    if chosen is None and set(options) - set(declared):
        hints.append(f"options of the installed models: {', '.join(sorted(declared))}")
    return hints


def _option_problem(models: dict[str, dict], chosen: dict | None, options: dict) -> str | None:
    """What is wrong with `options` for the chosen model (None: model auto, where every model
    that declares an option must take its value), in the server's words; None if nothing."""
    if not options:
        return None
    if chosen is not None:
        specs = {o["name"]: o for o in chosen.get("options") or ()}
        unknown = sorted(set(options) - set(specs))
        if unknown:
            takes = "; its options: " + "; ".join(map(_describe_option, specs.values())) \
                if specs else ": it takes no run-time options"
            return f"model {chosen['name']!r} has no option {', '.join(unknown)}{takes}"
        return _value_problem(chosen, specs, options)
    declared = {o["name"] for m in models.values() for o in m.get("options") or ()}
    unknown = sorted(set(options) - declared)
    if unknown:
        return (f"no installed model has option {', '.join(unknown)} (model 'auto' gives an "
                "option to the models that have it)")
    for m in models.values():
        specs = {o["name"]: o for o in m.get("options") or () if o["name"] in options}
        problem = _value_problem(m, specs, {k: options[k] for k in specs})
        if problem:
            return problem
    return None


def _describe_option(option: dict) -> str:
    """`kernel_size (one of [5, 7, 9], default 5)`, as the server describes an option."""
    values = f"one of {list(option['allowed'])}, " if option.get("allowed") is not None else ""
    if option.get("minimum") is not None:
        values += f"at least {option['minimum']:g}, "
    return f"{option['name']} ({values}default {option.get('default')})"


def _value_problem(model: dict, specs: dict[str, dict], options: dict) -> str | None:
    """A value the model's option does not take (its allowed values, its minimum)."""
    for name, value in options.items():
        allowed, minimum = specs[name].get("allowed"), specs[name].get("minimum")
        if allowed is not None and value not in allowed:
            return f"model {model['name']!r}: {name} must be one of {list(allowed)}, got {value!r}"
        if minimum is not None and value < minimum:
            return f"model {model['name']!r}: {name} must be at least {minimum:g}, got {value!r}"
    return None


def check_view_layers(report: Report, layer: str | None, mapping: bool,
                      server: str) -> Failure | None:
    """The server's refusal of the first frame for its view layers: a --layer the file does not
    have, or several view layers and nothing (--layer, --channels) to say which to denoise."""
    if layer == "all":
        return None  # one session per view layer, each found by name
    if layer:
        if any(name.startswith(layer + ".") for name in report.names):
            return None
        return server_failure(422, "missing_channels", f"no channels of view layer {layer!r}; "
                              f"the file's view layers are {list(report.layers)}, its channels "
                              f"{list(report.names)}", server, True)
    if len(report.layers) > 1 and not mapping:
        return server_failure(422, "ambiguous_channels", "the beauty is found in each of the "
                              f"view layers {list(report.layers)}; pass --channels", server,
                              False, report.layers)
    return None


def _names_channels(spec: str | list[str], buffer: str, names: tuple[str, ...]) -> bool:
    """Whether a mapping's value can name channels of the file: a list, every one of them;
    a layer name (any case), some channel `<layer>.<component>`; a depth mapping may also name
    one channel (the server's runtime.exr_channels reads the components)."""
    if not isinstance(spec, str):
        return all(c in names for c in spec)
    if buffer == "depth" and spec in names:
        return True
    return any(n.rpartition(".")[0].lower() == spec.lower() for n in names)


def check_mapping(report: Report, mapping: dict | None, server: str) -> Failure | None:
    """The server's refusal of the first frame for a --channels entry that names nothing in
    it (the run's 422 missing_channels, in its words)."""
    for buffer, spec in (mapping or {}).items():
        if not _names_channels(spec, buffer, report.names):
            return server_failure(422, "missing_channels", f"session mapping {buffer}={spec!r} "
                                  f"names channels that are not in the file; found "
                                  f"{list(report.names)}", server, True)
    return None
