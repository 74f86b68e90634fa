"""quietframe.wire: what the server and its clients share on the wire, the /v1 frame protocol
(`protocol`) and the byte layout of an EXR header (`exr_layout`). A leaf: standard library only
and nothing of quietframe's other folders, so the client (no onnxruntime), the runtime (no client
or service) and the service all import it."""
