"""``zfusion view PATH``: a recording in the Rerun viewer, once the file and a display are there."""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path

from ..errors import UserError

RRD_MAGIC = b"RRF2"  # how every Rerun recording file starts


def register(sub) -> None:
    p = sub.add_parser("view", help="open a recording in the Rerun viewer")
    p.add_argument("path")
    p.set_defaults(main=run)


def run(args) -> int:
    argv = viewer_argv(args.path, os.environ)
    os.execv(argv[0], argv)
    return 0  # not reached: the viewer replaces this process


def viewer_argv(path: str, env) -> list[str]:
    """The Rerun viewer's command line for ``zfusion view PATH`` (its server on loopback
    only), once the file is a recording and there is a display; else a :class:`UserError`."""
    file = Path(path)
    if not file.is_file():
        raise UserError(f"no such recording: {path}; give the .rrd file a run wrote (zfusion run --rrd PATH)")
    with file.open("rb") as f:
        if f.read(len(RRD_MAGIC)) != RRD_MAGIC:
            raise UserError(f"{path} is not a Rerun recording (it does not start as an .rrd file does); "
                            f"check that the file is whole and is the one a run wrote")
    if sys.platform.startswith("linux") and not (env.get("DISPLAY") or env.get("WAYLAND_DISPLAY")):
        raise UserError(f"no display here (neither DISPLAY nor WAYLAND_DISPLAY is set): copy {path} to a machine "
                        f"with one, or run rerun --serve-web --bind 127.0.0.1 {path} and tunnel ports 9090 and "
                        f"9876 (README)", code=1)
    exe = shutil.which("rerun") or str(Path(sys.executable).with_name("rerun"))
    return [exe, "--bind", "127.0.0.1", path]
