"""Run a Blender render in a child process with a timeout (the bpy module can hang at exit after a
render, see bareesa_addon/demo.py): the tools' ``--child`` mode renders, then leaves with ``os._exit``."""

import argparse
import os
import subprocess
import sys
import traceback
from pathlib import Path


#: Where the tools write the README's pictures.
IMAGES = Path(__file__).resolve().parents[1] / "docs" / "images"


def render_parser(doc, width, timeout):
    """A tool's argument parser with what every picture tool takes: --out, --width, --timeout and the
    hidden --child: -> ArgumentParser (add the tool's own arguments)."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    parser.add_argument("--out", type=Path, default=IMAGES, help="folder of the pictures (default docs/images)")
    parser.add_argument("--width", type=int, default=width, help=f"picture width in pixels (default {width})")
    parser.add_argument("--timeout", type=float, default=timeout, help="seconds the render may take")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    return parser


def finish_child(render, *args):
    """In the child: render(*args), print any traceback, flush and leave at once (exit status 0 / 1)."""
    code = 0
    try:
        render(*args)
    except Exception:  # noqa: BLE001 - reported, then the fast exit
        traceback.print_exc()
        code = 1
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def run_child(script, argv, timeout, name):
    """In the parent: run ``script --child argv...`` under ``timeout`` seconds: -> exit status."""
    try:
        return subprocess.run([sys.executable, str(script), "--child", *map(str, argv)], timeout=timeout).returncode
    except subprocess.TimeoutExpired:
        print(f"{name}: the render took more than {timeout:g} s and was stopped", file=sys.stderr)
        return 1
