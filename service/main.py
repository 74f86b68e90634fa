"""Build the app: lifespan loads the models and holds the registries; routers do the rest.

Run with `quietframe serve`, or `uvicorn --factory quietframe.service.main:create_app`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator
from concurrent.futures import ThreadPoolExecutor

import uvicorn
from fastapi import Depends, FastAPI
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles

from quietframe.service import frames, guard, logs
from quietframe.service.deps import require_auth
from quietframe.service.errors import install_handlers
from quietframe.service.guard import RequestGuard
from quietframe.service.metrics import Metrics
from quietframe.service.model_registry import ModelRegistry
from quietframe.service.routers import health, models, sessions
from quietframe.service.sessions import SessionRegistry
from quietframe.service.settings import Settings

log = logging.getLogger("quietframe.service")

DESCRIPTION = """Frame-sequence denoising for path-traced renders.

One **session** per camera sequence keeps the model's temporal history on the server. Create
it with the frame size, then POST each frame (one multi-layer EXR with colour and AOVs) in
order; each response is the denoised EXR. Renderer channel names of Blender Cycles, Arnold,
RenderMan, V-Ray and plain `R,G,B` + `albedo.*`, `N.*`, `Z` are recognised; a session may pass its
own mapping. Errors are JSON `{"error": code, "detail": message}`."""


async def _expire_loop(registry: SessionRegistry, period_s: float) -> None:
    while True:
        await asyncio.sleep(period_s)
        registry.expire()


def create_app(settings: Settings | None = None,
               loaded: ModelRegistry | None = None) -> FastAPI:
    """The service; `loaded`: an already loaded model registry for these settings (tests that start
    many apps load the models once), else loaded at start-up."""
    settings = settings or Settings()

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        guard.summarise_accept_failures(asyncio.get_running_loop())
        frames.configure_io(settings.model_threads)  # decoding runs when the model does not
        registry_models = loaded or await asyncio.to_thread(ModelRegistry, settings)
        await asyncio.to_thread(registry_models.warm_up)
        pool = ThreadPoolExecutor(settings.worker_count, thread_name_prefix="quietframe-frame")
        registry = await asyncio.to_thread(
            SessionRegistry, settings, registry_models, app.state.metrics, pool
        )  # reads the durable sessions' files: off the event loop
        app.state.models, app.state.sessions = registry_models, registry
        period = min(30.0, settings.session_ttl_s / 4)
        reaper = asyncio.create_task(_expire_loop(registry, period))
        log.info(
            "ready",
            extra={
                "models": registry_models.names,
                "default": registry_models.default,
                "workers": settings.worker_count,
                "threads": settings.model_threads,
                "state_dir": str(settings.state_dir) if settings.state_dir else None,
            },
        )
        try:
            yield
        finally:
            reaper.cancel()
            pool.shutdown(wait=True)
            registry.close_streams()
            if loaded is None:  # a registry handed in is its owner's to close
                registry_models.close()

    app = FastAPI(
        title="quietframe",
        version="1",
        description=DESCRIPTION,
        lifespan=lifespan,
        docs_url=None,  # served from the package below: a farm network may have no internet
        redoc_url=None,
    )
    app.state.settings = settings
    app.state.metrics = Metrics()
    install_handlers(app, app.state.metrics.count_error)
    app.add_middleware(RequestGuard, settings=settings, count_error=app.state.metrics.count_error)
    auth = [Depends(require_auth)]
    app.include_router(sessions.router, prefix="/v1", dependencies=auth)
    app.include_router(models.router, prefix="/v1", dependencies=auth)
    app.include_router(health.router)
    _document_limits(app, settings)
    _serve_docs(app)
    return app


DOCS_ASSETS = "/docs/assets"


def _serve_docs(app: FastAPI) -> None:
    """Swagger UI at /docs from the files of the `swagger-ui-bundle` wheel (serve extra), not
    from a CDN, so the page works on an offline farm; without the wheel, FastAPI's CDN page."""
    try:  # optional: a server without it still serves /docs
        from swagger_ui_bundle import swagger_ui_path
    except ImportError:
        swagger_ui_path = None
    if swagger_ui_path is None:
        log.warning("swagger-ui-bundle is not installed: /docs loads Swagger UI from a CDN")
        assets = {}
    else:
        app.mount(DOCS_ASSETS, StaticFiles(directory=swagger_ui_path), name="docs-assets")
        assets = {
            "swagger_js_url": f"{DOCS_ASSETS}/swagger-ui-bundle.js",
            "swagger_css_url": f"{DOCS_ASSETS}/swagger-ui.css",
            "swagger_favicon_url": f"{DOCS_ASSETS}/favicon-32x32.png",
        }

    @app.get("/docs", include_in_schema=False)
    async def docs() -> HTMLResponse:
        return get_swagger_ui_html(openapi_url=app.openapi_url or "/openapi.json",
                                   title="quietframe API", **assets)


def _document_limits(app: FastAPI, settings: Settings) -> None:
    """The OpenAPI describes this server: its frame-size maxima (settings, not constants), and
    the bearer scheme only when a token is set."""
    build = app.openapi

    def openapi() -> dict:
        schema = build()  # cached by FastAPI; patching again is idempotent
        fields = schema["components"]["schemas"]["SessionCreate"]["properties"]
        fields["width"]["maximum"] = settings.max_width
        fields["height"]["maximum"] = settings.max_height
        if settings.auth_token is None:
            schema["components"].pop("securitySchemes", None)
            for path in schema["paths"].values():
                for operation in path.values():
                    operation.pop("security", None)
        return schema

    app.openapi = openapi  # type: ignore[method-assign]


def run(host: str, port: int, settings: Settings | None = None) -> None:
    """Serve until interrupted (the `quietframe serve` command)."""
    settings = settings or Settings()
    logs.configure(settings.log_level, settings.log_json)
    # Connections that never finish their headers are closed, and at most the cap are open
    # (guard.py); `uvicorn --factory` serves without these.
    cap = guard.connection_cap(settings.max_connections)
    protocol = guard.guarded_protocol(settings.header_timeout_s, cap)
    uvicorn.run(
        create_app(settings),
        host=host,
        port=port,
        http=protocol,
        ws="none",  # no WebSocket routes: an upgrade request is a plain HTTP request
        log_config=None,
        timeout_graceful_shutdown=30,
    )
