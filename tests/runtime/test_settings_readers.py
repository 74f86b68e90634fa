"""The runtime's and the client's settings readers (runtime/settings.py, client/settings.py):
defaults, values read from the environment, errors that name the variable, and the runtime's
once-per-process read that a test can have done again."""

from __future__ import annotations

from pathlib import Path

import pytest

from quietframe.client.settings import ClientSettings, client_settings
from quietframe.runtime.settings import (
    DEFAULT_MAX_MEMORY_MB,
    RuntimeSettings,
    runtime_settings,
)
from quietframe.runtime.tiling import max_memory_mb_default


def test_runtime_defaults_when_unset():
    settings = RuntimeSettings.from_environ({})
    assert settings.ops_library is None
    assert settings.max_memory_mb == DEFAULT_MAX_MEMORY_MB


def test_runtime_values_from_the_environment():
    settings = RuntimeSettings.from_environ(
        {"QUIETFRAME_OPS_LIBRARY": "/x/libquietframe_ops.so", "QUIETFRAME_MAX_MEMORY_MB": "6144"}
    )
    assert settings.ops_library == Path("/x/libquietframe_ops.so")
    assert settings.max_memory_mb == 6144.0
    # set but empty: the installed library, as before the reader existed
    assert RuntimeSettings.from_environ({"QUIETFRAME_OPS_LIBRARY": ""}).ops_library is None


@pytest.mark.parametrize("text", ["lots", "", "0", "-5", "nan", "inf"])
def test_a_bad_memory_bound_names_the_variable(text):
    with pytest.raises(ValueError, match="QUIETFRAME_MAX_MEMORY_MB=.*expected a number of MiB"):
        RuntimeSettings.from_environ({"QUIETFRAME_MAX_MEMORY_MB": text})


def test_runtime_settings_are_read_once_and_again_on_request(runtime_env):
    runtime_env("QUIETFRAME_MAX_MEMORY_MB", "2048")
    assert max_memory_mb_default() == 2048.0
    first = runtime_settings()
    runtime_env("QUIETFRAME_MAX_MEMORY_MB", "4096")  # re-reads
    assert runtime_settings() is not first and max_memory_mb_default() == 4096.0


def test_client_settings_from_the_environment(monkeypatch):
    assert ClientSettings.from_environ({}) == ClientSettings()
    settings = ClientSettings.from_environ({
        "QUIETFRAME_SERVER": "http://denoise:8000", "QUIETFRAME_TOKEN": "s3cret",
        "QUIETFRAME_MODELS_DIR": "/models", "QUIETFRAME_DEFAULT_MODEL": "nbg-g2",
    })
    assert settings == ClientSettings("http://denoise:8000", "s3cret", Path("/models"), "nbg-g2")
    empty = ClientSettings.from_environ(
        {"QUIETFRAME_MODELS_DIR": "", "QUIETFRAME_DEFAULT_MODEL": ""}
    )
    assert empty.models_dir is None and empty.default_model is None
    monkeypatch.setenv("QUIETFRAME_SERVER", "http://elsewhere:1")  # read at each call
    assert client_settings().server == "http://elsewhere:1"
