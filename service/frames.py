"""EXR bytes <-> canonical float32 buffers, in three steps so that a bad request is refused
before any pixel is decoded (the names the service and the tests use, from their modules in
runtime/, below the service, because the scene readers decode Cycles frames with them too):

1. `read_header` (runtime/exr_header.py) checks the EXR header (size limits, channel list,
   windows, flags), whose bytes the one EXR header reader walks in pure Python
   (wire/exr_layout.py, shared with the client's pre-flight; the one attribute reader);
2. `resolve` (runtime/exr_channels.py) maps the header's channel names onto the canonical
   buffers (the one renderer alias table, ALIASES, or the session's own mapping), naming what
   was found and what was expected when something is missing;
3. `decode` / `encode` (runtime/exr_codec.py) read the pixels with OpenEXR into planar
   (C, H, W) float32 buffers and write the input back with the denoised colour in place of the
   beauty's (runtime/exr_warnings.py turns the binding's printed warnings into log fields).
"""

from quietframe.runtime.exr_channels import (
    ALIASES,
    COMPONENTS,
    Alias,
    Source,
    for_model,
    resolve,
    validate_mapping,
)
from quietframe.runtime.exr_codec import (
    LOSSY_CODECS,
    DecodedFrame,
    Part,
    configure_io,
    decode,
    encode,
    encode_denoised,
    output_channels,
    output_compression,
    output_dtypes,
)
from quietframe.runtime.exr_header import (
    ChannelInfo,
    ExrHeader,
    HeaderScan,
    TruncatedExr,
    check_windows,
    read_header,
)
from quietframe.wire.exr_layout import attribute, attribute_number, attribute_value

__all__ = [
    "ALIASES",
    "COMPONENTS",
    "LOSSY_CODECS",
    "Alias",
    "ChannelInfo",
    "DecodedFrame",
    "ExrHeader",
    "HeaderScan",
    "Part",
    "Source",
    "TruncatedExr",
    "attribute",
    "attribute_number",
    "attribute_value",
    "check_windows",
    "configure_io",
    "decode",
    "encode",
    "encode_denoised",
    "for_model",
    "output_channels",
    "output_compression",
    "output_dtypes",
    "read_header",
    "resolve",
    "validate_mapping",
]
