"""quietframe.client: HTTP clients of the denoising service and the `quietframe` CLI."""

from quietframe.client.api import AsyncClient, Client
from quietframe.client.core import FrameResult, QuietframeError, RetryPolicy

__all__ = ["AsyncClient", "Client", "FrameResult", "QuietframeError", "RetryPolicy"]
