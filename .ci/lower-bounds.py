"""Print pip constraints that pin every dependency of pyproject.toml to its lower bound.

``make test-oldest`` installs armfit with these constraints, so the suite runs against the
oldest versions the project claims to support (``name>=X`` becomes ``name==X``).
"""

import re
import sys
import tomllib
from pathlib import Path

project = tomllib.loads(Path(sys.argv[1] if len(sys.argv) > 1 else "pyproject.toml")
                        .read_text())["project"]
specs = list(project["dependencies"])
for extra in project.get("optional-dependencies", {}).values():
    specs += extra
for spec in specs:
    # extras (``name[extra]>=X``) are dropped: a constraint names the package only
    m = re.fullmatch(r"\s*([A-Za-z0-9_.\-]+)(?:\[[^\]]*\])?\s*>=\s*([^,;\s]+).*", spec)
    if m is None:
        sys.exit(f"lower-bounds: no '>=' lower bound in {spec!r}")
    print(f"{m.group(1)}=={m.group(2)}")
