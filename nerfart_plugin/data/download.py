"""Sample captures by one command: ``python -m nerfart_plugin.data.download NAME [--dest DIR]``.

The captures the documentation uses, from their public releases, each file checked against the size
and SHA-256 recorded in ``assets/samples.json`` (a file that does not match is refused and removed;
the others stay). Files already present with the right content are not downloaded again, so an
interrupted download resumes where it stopped.

    python -m nerfart_plugin.data.download --list
    python -m nerfart_plugin.data.download girl                 # -> data/samples/girl
    python -m nerfart_plugin data=h3ds data.path=data/samples/girl +prompt=Joker

``--mirror`` reads from another base address (a folder or URL holding ``<name>/<file>``) instead of the
releases, e.g. a copy on a machine without internet access.
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import sys
import urllib.request
from importlib import resources
from pathlib import Path
from typing import Any, Optional

from tqdm import tqdm

from nerfart_plugin.errors import DataError, NerfArtError, RunInterrupted
from nerfart_plugin.utils.io import atomic_path, file_sha256

log = logging.getLogger("nerfart_plugin")

DEFAULT_DEST = Path("data") / "samples"


def manifest() -> dict[str, Any]:
    """name -> {description, base_url, data (the data= config), files: {relative path: [bytes, sha256]}}."""
    return json.loads(resources.files("nerfart_plugin").joinpath("assets/samples.json").read_text())


def intact(path: Path, size: int, digest: str) -> bool:
    return path.is_file() and path.stat().st_size == size and file_sha256(path) == digest


def fetch(source: str, target: Path, size: int, digest: str) -> None:
    """Copy ``source`` (a URL or a local path) to ``target`` atomically, refusing content that does not
    match ``size`` and ``digest``."""
    with atomic_path(target) as tmp:
        if "://" in source:
            with urllib.request.urlopen(source, timeout=60) as response, open(tmp, "wb") as out:
                shutil.copyfileobj(response, out)
        else:
            shutil.copyfile(source, tmp)
        got_size, got = Path(tmp).stat().st_size, file_sha256(tmp)
        if got_size != size or got != digest:
            raise DataError(f"{source}: got {got_size} bytes with SHA-256 {got[:12]}..., expected {size} bytes with "
                            f"{digest[:12]}...: the file at the source changed or the transfer broke; nothing was "
                            "kept. Try again, or pass --mirror with a copy you trust.")


def download(name: str, dest: Path = DEFAULT_DEST, mirror: Optional[str] = None) -> Path:
    """Download sample ``name`` into ``dest/name`` (see the module docstring); returns that folder."""
    samples = manifest()
    if name not in samples:
        raise NerfArtError(f"no sample named {name!r}; choose one of: {', '.join(sorted(samples))}.")
    entry = samples[name]
    base = f"{mirror.rstrip('/')}/{name}" if mirror else entry["base_url"]
    folder = Path(dest).expanduser() / name
    todo = [(rel, size, digest) for rel, (size, digest) in sorted(entry["files"].items())
            if not intact(folder / rel, size, digest)]
    for rel, size, digest in tqdm(todo, desc=f"downloading {name}", unit="file"):
        source = f"{base}/{rel}" if "://" in base else str(Path(base) / rel)
        try:
            fetch(source, folder / rel, size, digest)
        except OSError as exc:
            raise DataError(f"could not read {source} ({exc}); check the connection (or --mirror) and run the "
                            f"same command again: the {len(entry['files']) - len(todo)} files already here are "
                            "kept.") from exc
    log.info("%s: %d files in %s (%d downloaded); use it with: python -m nerfart_plugin data=%s data.path=%s",
             name, len(entry["files"]), folder, len(todo), entry["data"], folder)
    return folder


def main(argv: Optional[list[str]] = None) -> int:
    p = argparse.ArgumentParser(prog="python -m nerfart_plugin.data.download", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("name", nargs="?", help="the sample to download (--list shows them)")
    p.add_argument("--dest", type=Path, default=DEFAULT_DEST, help=f"where to put it (default {DEFAULT_DEST}/NAME)")
    p.add_argument("--mirror", default=None, help="a folder or URL holding NAME/<files>, instead of the releases")
    p.add_argument("--list", action="store_true", help="list the samples")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    samples = manifest()
    if args.list or not args.name:
        for name, entry in sorted(samples.items()):
            mb = sum(size for size, _ in entry["files"].values()) / 1e6
            log.info("%-18s %6.1f MB  %s", name, mb, entry["description"])
        return 0
    try:
        download(args.name, args.dest, args.mirror)
    except NerfArtError as exc:
        log.error("%s: %s", type(exc).__name__, exc)
        return 2
    except KeyboardInterrupt:  # the file in progress is discarded (written atomically); the finished ones stay
        log.error("RunInterrupted: interrupted; the files already downloaded are kept: run the same command again "
                  "to resume")
        return RunInterrupted.exit_code
    return 0


if __name__ == "__main__":
    sys.exit(main())
