"""Export the hand-made levels as Kinetix JSON files next to their designs, and check them.

    python -m engine.levels.handmade.build                 # (re)write every <name>.json, then check each one
    python -m engine.levels.handmade.build --check         # only check that the files exist and match
    python -m engine.levels.handmade.build s_hop_over      # just some levels

Exit status 1 lists the levels whose design is invalid or whose file does not load back identical.

This module is a script: import `engine.levels.handmade.files` instead (importing a submodule named `build`
would replace the package's `handmade.build` function with this module).
"""

from __future__ import annotations

import sys

from impulse.engine.levels.handmade.files import main

if __name__ == "__main__":
    sys.exit(main())
