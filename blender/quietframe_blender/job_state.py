"""What the panel shows about the job under way or the last one: written by the upload thread
(through its progress callback), read by the UI on the main thread."""

from __future__ import annotations

import threading

from .denoise_job import JobResult, Progress


class JobState:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.running = False
        self.done = 0
        self.total = 0
        self.message = ""
        self.error = ""
        self.last_result: JobResult | None = None  # for scripts: the last job's frames
        self.cancel: threading.Event | None = None  # set to stop the job under way

    def start(self, total: int, cancel: threading.Event, message: str = "starting") -> None:
        with self._lock:
            self.running, self.done, self.total = True, 0, total
            self.message, self.error, self.cancel = message, "", cancel

    def update(self, progress: Progress) -> None:
        with self._lock:
            self.done, self.total, self.message = progress.done, progress.total, progress.message

    def say(self, message: str) -> None:
        with self._lock:
            self.message = message

    def end(self, result: JobResult | None, error: str = "") -> None:
        with self._lock:
            self.running, self.cancel = False, None
            self.last_result = result
            self.error = error
            if result is not None:
                self.done = len(result.outcomes)
                self.message = result.summary()
            elif error:
                self.message = "stopped"

    def snapshot(self) -> tuple[bool, int, int, str, str]:
        with self._lock:
            return self.running, self.done, self.total, self.message, self.error


STATE = JobState()  # the operator's job
LIVE_STATE = JobState()  # denoising while rendering (live.py)
