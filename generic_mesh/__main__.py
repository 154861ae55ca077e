"""Rebuild the committed generic meshes: `python -m generic_mesh [resolution ...]`."""
import sys

from generic_mesh import RESOLUTIONS, path_of
from generic_mesh.builder import build, report


def main(argv=None) -> int:
    names = (argv if argv is not None else sys.argv[1:]) or list(RESOLUTIONS)
    for r in names:
        model = build(r)
        model.save(path_of(r))
        print(report(model, r))
        print(f"  written {path_of(r)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
