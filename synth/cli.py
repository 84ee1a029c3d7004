"""``edmcgs synth SCENE ...``: each scene family has its own builder and flags.

    edmcgs synth jumpingjack|kick|lego|mutant ...   Gaussian scenes (``build``)
    edmcgs synth traffic|traffic-pan ...            the composited DAVIS346-like street (``traffic_build``)
    edmcgs synth street3d ...                       a handheld camera in a ray-cast 3D street
                                                    (``street3d_build``)
"""

from __future__ import annotations

import sys
from importlib import import_module

BUILDERS = {"traffic": "edmcgs.synth.traffic_build", "traffic-pan": "edmcgs.synth.traffic_build",
            "street3d": "edmcgs.synth.street3d_build"}
"""Scenes with a builder of their own; every other scene is ``edmcgs.synth.build``'s."""


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    module = BUILDERS.get(argv[0] if argv else "", "edmcgs.synth.build")
    return import_module(module).main(argv)


if __name__ == "__main__":
    sys.exit(main())
