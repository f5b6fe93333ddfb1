"""Run the BaRe-ESA Blender demo headless from a source checkout.

    python tools/demo_blender.py --out bareesa_demo             (the bpy module)
    blender -b --factory-startup -P tools/demo_blender.py -- --out bareesa_demo

See bareesa_addon/demo.py for what it does.
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bareesa_addon.demo import console_main  # noqa: E402

if __name__ == "__main__":
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
    sys.exit(console_main(argv))
