#!/usr/bin/env bash
# The 3D Slicer Extensions Index's checks of GeoPose, run the way its CI runs them on a catalog
# entry: clone the repository (full history, as the Index does), validate GeoPose.json against the
# catalog schema, then check the clone: category, repository URL and name, the top-level
# CMakeLists.txt (project name = catalog file name, icon and screenshot URLs), the licence file,
# contributors written "First Last (Organisation)", and the size of the clone with its .git folder
# (at most 100 MB). Offline: the icon and screenshot URLs are checked to name image files committed
# in the clone (the Index downloads them and checks their content type), and what only the Index
# can check is listed at the end (the GitHub topic, the PyTorch entry in the Index).
#
# Usage: scripts/index_check.sh [--branch NAME] [--fresh-history]
#   --branch NAME    the branch that would be published (default: the current one)
#   --fresh-history  measure a one-commit public history of that branch's files instead of its history
# Exit status: the number of failed checks. Needs git, du and a Python with jsonschema (.venv).
set -uo pipefail

REPO=$(cd "$(dirname "$0")/.." && pwd)
PY=${PYTHON:-$REPO/.venv/bin/python}
BRANCH=$(git -C "$REPO" rev-parse --abbrev-ref HEAD)
FRESH=0
while [ $# -gt 0 ]; do
  case $1 in
    --branch) BRANCH=$2; shift 2 ;;
    --fresh-history) FRESH=1; shift ;;
    *) echo "unknown argument $1 (see the header of $0)" >&2; exit 64 ;;
  esac
done
SCHEMA=${SLICER_CATALOG_SCHEMA:-$REPO/../shared/slicer-api/slicer-extension-catalog-entry-schema-v1.0.2.json}
LIMIT_BYTES=100000000  # the Index's 100 MB, decimal megabytes

WORK=$(mktemp -d "${TMPDIR:-/tmp}/geopose-index-check.XXXXXX")
trap 'rm -rf "$WORK"' EXIT
CLONE=$WORK/clone
if [ "$FRESH" = 1 ]; then
  # What a fresh public history would be: the branch's files, committed once.
  mkdir -p "$CLONE"
  git -C "$REPO" archive "$BRANCH" | tar -x -C "$CLONE"
  git -C "$CLONE" init -q -b "$BRANCH"
  git -C "$CLONE" add -A
  git -C "$CLONE" -c user.name=check -c user.email=check@example.invalid commit -q -m "GeoPose for 3D Slicer"
  git -C "$CLONE" gc -q --aggressive
  HISTORY="fresh one-commit history of $BRANCH"
else
  # As the Index clones the published repository: a full clone of the branch it would hold.
  git clone -q --no-local --single-branch --branch "$BRANCH" "$REPO" "$CLONE" || exit 1
  HISTORY="history of $BRANCH ($(git -C "$CLONE" rev-list --count HEAD) commits)"
fi

"$PY" - "$CLONE" "$SCHEMA" "$LIMIT_BYTES" "$HISTORY" <<'PYTHON'
import json
import re
import subprocess
import sys
from pathlib import Path
from urllib.parse import urlsplit

import jsonschema

clone, schema_path, limit, history = Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
failed = []


def check(name, ok, detail):
    print(f"- {'PASS' if ok else 'FAIL'}: {name}: {detail}")
    if not ok:
        failed.append(name)


entry_file = clone / "GeoPose.json"
entry = json.loads(entry_file.read_text())
extension = entry_file.stem
try:
    jsonschema.validate(entry, json.loads(schema_path.read_text()))
    check("catalog schema", True, f"{entry_file.name} is valid against {schema_path.name}")
except jsonschema.ValidationError as exc:
    check("catalog schema", False, f"{exc.message} at {'/'.join(map(str, exc.absolute_path))}")

# Categories the Index accepts that could describe GeoPose (its full list is longer).
check("category", entry.get("category") in {"Registration", "Neuroimaging", "IGT", "Analysis", "Quantification"},
      repr(entry.get("category")))
url = urlsplit(entry.get("scm_url", ""))
check("scm_url", url.scheme in ("git", "https") and "://" in entry.get("scm_url", ""), entry.get("scm_url"))
repo_name = Path(url.path).stem
check("repository name", "slicer" in repo_name.lower(), f"{repo_name!r} (the Index wants 'Slicer' in it)")

cmake = (clone / "CMakeLists.txt").read_text()
projects = re.findall(r"project\s*\(\s*([^\s\)]+)", cmake, re.I)
check("CMake project name", bool(projects) and projects[0] == extension,
      f"project({projects[0] if projects else '?'}) for the catalog file {entry_file.name}")


def committed_image(address):
    """The file a raw.githubusercontent.com address names in the clone, if it is a PNG, JPEG or GIF."""
    parts = urlsplit(address).path.strip("/").split("/")  # owner / repository / revision / path...
    path = clone.joinpath(*parts[3:])
    head = path.read_bytes()[:8] if path.is_file() else b""
    return head.startswith((b"\x89PNG", b"\xff\xd8\xff", b"GIF8"))


icons = re.findall(r'set\s*\(EXTENSION_ICONURL\s*"([^"]+)"\s*\)', cmake, re.I)
shots = re.findall(r'set\s*\(EXTENSION_SCREENSHOTURLS\s*"([^"]+)"\s*\)', cmake, re.I)
addresses = icons[:1] + (shots[0].split() if shots else [])
check("icon and screenshot URLs", bool(icons) and bool(shots) and all(a.startswith("http") and committed_image(a) for a in addresses),
      f"{len(addresses)} addresses, each naming an image committed here" if addresses else "missing")

licences = [n for n in ("LICENSE", "LICENCE", "License.txt", "license.txt", "LICENSE.txt", "COPYING", "COPYING.txt")
            if (clone / n).is_file()]
check("licence file", bool(licences), ", ".join(licences) or "none in the repository root")

listed = re.search(r'set\s*\(EXTENSION_CONTRIBUTORS\s*"([^"]*)"\s*\)', cmake)
people = [c.strip() for c in listed.group(1).split(",")] if listed else []
person = re.compile(r"^[A-Z][\w'.-]*( [A-Za-z][\w'.-]*)* [A-Z][\w'-]+ \([^()]+\)$")
team = re.compile(r"\b(maintainers|contributors|team|developers|authors|group|lab)\b", re.I)
not_people = [c for c in people if not person.match(c) or team.search(c.split("(")[0])]
check("contributors", bool(people) and not not_people,
      "written 'First Last (Organisation)'" if people and not not_people else
      f"not a person's 'First Last (Organisation)': {not_people or 'none listed'}")

tracked = subprocess.run(["du", "-sb", "--exclude=.git", str(clone)], capture_output=True, text=True, check=True)
total = subprocess.run(["du", "-sb", str(clone)], capture_output=True, text=True, check=True)
files_bytes, total_bytes = int(tracked.stdout.split()[0]), int(total.stdout.split()[0])
check("repository size", total_bytes <= limit,
      f"{total_bytes / 1e6:.1f} MB with .git ({(total_bytes - files_bytes) / 1e6:.1f} MB .git + {files_bytes / 1e6:.1f} MB files; "
      f"{history}) against {limit / 1e6:.0f} MB")

print("- NOT CHECKED HERE (the Index checks them online): the icon and screenshot addresses answer with an image "
      "content type; the GitHub repository carries the topic '3d-slicer-extension'; the build dependency 'PyTorch' "
      "has an entry in the Index.")
print(f"{len(failed)} check(s) failed" + (f": {', '.join(failed)}" if failed else ""))
sys.exit(len(failed))
PYTHON
