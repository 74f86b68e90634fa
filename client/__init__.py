"""quietframe.client: HTTP clients of the denoising service and the `quietframe` CLI."""

from quietframe.client.api import AsyncClient, Client, FrameResult, QuietframeError, RetryPolicy

__all__ = ["AsyncClient", "Client", "FrameResult", "QuietframeError", "RetryPolicy"]
