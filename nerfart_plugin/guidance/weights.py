"""Offline-first lookup of pretrained weight files (CLIP, VGG).

Policy: look in the local caches first; only touch the network when downloads
are explicitly allowed (``allow_download=True`` in the config or the
environment variable ``NERFART_ALLOW_DOWNLOAD=1``) AND a 2-second TCP connect
to the host succeeds. Otherwise fail at once with a WeightsMissingError that
says what is missing, where it was looked for and how to supply it -- never a
minute of retries in the middle of a run.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
from urllib.parse import urlparse

log = logging.getLogger(__name__)

ALLOW_DOWNLOAD_ENV = "NERFART_ALLOW_DOWNLOAD"
CONNECT_TIMEOUT_S = 2.0


def downloads_allowed(flag: bool | None) -> bool:
    """``flag`` if given, else the ``NERFART_ALLOW_DOWNLOAD`` env var (1/true/yes)."""
    if flag is not None:
        return bool(flag)
    return os.environ.get(ALLOW_DOWNLOAD_ENV, "").strip().lower() in {"1", "true", "yes", "on"}


def host_reachable(url_or_host: str, timeout: float = CONNECT_TIMEOUT_S) -> bool:
    """True if a TCP connection to the host (port 443, or the HTTPS proxy from
    ``HTTPS_PROXY``/``https_proxy`` if set) opens within ``timeout`` seconds.
    DNS resolution is bounded by the same timeout (run in a daemon thread)."""
    proxy = os.environ.get("HTTPS_PROXY") or os.environ.get("https_proxy")
    target = proxy or url_or_host
    parsed = urlparse(target if "://" in target else f"https://{target}")
    host = parsed.hostname or target
    port = parsed.port or (443 if parsed.scheme == "https" else 80)
    result: list[bool] = []

    def probe() -> None:
        try:
            with socket.create_connection((host, port), timeout=timeout):
                result.append(True)
        except OSError as exc:
            log.info("No connection to %s:%d (%s)", host, port, exc)
            result.append(False)

    th = threading.Thread(target=probe, daemon=True)
    th.start()
    th.join(timeout + 0.5)
    return bool(result and result[0])


def looks_like_path(value: str) -> bool:
    """Heuristic: a config value meant as a file path rather than a tag."""
    return (
        os.sep in value
        or "/" in value
        or value.startswith("~")
        or value.endswith((".pt", ".pth", ".bin", ".safetensors", ".ckpt", ".npz"))
    )


def download_hint(flag: bool | None, host: str) -> str:
    """One sentence on why no download was attempted (for error messages)."""
    if not downloads_allowed(flag):
        return (
            f"Downloads are disabled (enable with guidance.allow_download=true or {ALLOW_DOWNLOAD_ENV}=1 "
            "on a machine with internet)."
        )
    return f"Downloads are enabled but {host} is not reachable (no internet?)."
