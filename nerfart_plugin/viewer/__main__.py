"""``python -m nerfart_plugin.viewer RUN [--host H] [--port P]``: serve a finished run in the browser."""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path
from typing import Sequence

from nerfart_plugin.errors import NerfArtError

REMOTE_HINT = ("On a remote machine, forward the port over SSH (ssh -L {port}:127.0.0.1:{port} user@machine) and "
               "open the URL locally; --host 0.0.0.0 serves every network interface, so anyone who can reach "
               "this machine can view (not change) the run.")


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m nerfart_plugin.viewer",
                                description="Fly through a finished reconstruction or stylization in the browser: "
                                            "channels, source | stylized, the strength dial, mixes, camera paths.")
    p.add_argument("run", metavar="RUN", help="a run folder (outputs/reconstructions/<run>, "
                                              "outputs/stylizations/<run>) or a .ckpt in one")
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=int, default=8080, help="port (default 8080; the next free one if taken)")
    p.add_argument("--device", default="auto", help="auto | cpu | cuda | cuda:N | mps")
    p.add_argument("--max-side", type=int, default=512, help="long side (pixels) of the finest frame")
    p.add_argument("--compile", default="auto", choices=("auto", "on", "off"),
                   help="compiled frames (auto: compiled in the background where a C++ compiler or Triton is "
                   "available; eager frames meanwhile)")
    p.add_argument("--checkpoint", default="final.ckpt", help="the checkpoint in RUN (last.ckpt: an unfinished run)")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    if not 0 <= args.port <= 65535:
        p.exit(2, f"error: --port {args.port}: give a port from 1 to 65535 (0: any free port).\n")
    if args.max_side < 16:
        p.exit(2, f"error: --max-side {args.max_side}: give at least 16 pixels.\n")
    if not Path(args.run).exists():  # answered before the training stack loads
        p.exit(2, f"error: {args.run} does not exist: give a run folder (outputs/reconstructions/<run> or "
                  "outputs/stylizations/<run>) or a .ckpt in one.\n")
    from nerfart_plugin.viewer import open_viewer

    try:
        viewer = open_viewer(args.run, host=args.host, port=args.port, device=args.device, max_side=args.max_side,
                             checkpoint=args.checkpoint, compile=args.compile)
    except NerfArtError as exc:
        p.exit(2, f"error: {exc}\n")
    if args.port and viewer.port != args.port:
        logging.getLogger("nerfart_plugin.viewer").warning("port %d is taken: serving on port %d instead",
                                                           args.port, viewer.port)
    if args.host not in ("127.0.0.1", "localhost", "::1"):
        logging.getLogger("nerfart_plugin.viewer").warning(
            "serving on %s: anyone who can reach this machine on port %d can view the run and use its panels "
            "(there is no login)", args.host, viewer.port)
    print(f"nerfart_plugin viewer: open {viewer.url} in a browser (Ctrl-C to stop)", flush=True)
    print(REMOTE_HINT.format(port=viewer.port), flush=True)
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        viewer.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
