"""``geopose view``: the browser app (:mod:`geopose.web`). The arguments are checked before
the web packages are imported, so a wrong address or input path is one line and exit code 2."""

from __future__ import annotations

import argparse
import importlib.util
import tempfile
from pathlib import Path

from ..errors import InputError
from ..register.cli import options_from_args, registration_option_args
from .access import LOOPBACK, bind_token

#: Packages of the ``web`` extra.
WEB_PACKAGES = ("trame", "trame_slicer", "slicer")
DEFAULT_PORT = 8080


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("view", help="register a case and review it in the browser (needs the web extra)")
    p.add_argument("--case", default="", help="case folder holding cta.nii.gz, dsa_pa.dcm and dsa_lat.dcm (a geopose phantom/demo case)")
    p.add_argument("--cta", default="", help="CTA volume (NIfTI, NRRD, MHA or a DICOM series folder)")
    p.add_argument("--dsa-pa", default="", help="PA DSA run")
    p.add_argument("--dsa-lat", default="", help="lateral DSA run")
    p.add_argument("--demo", action="store_true", help="write the demo's phantom case (geopose demo's, 1 mm) into --out and fill it in")
    p.add_argument("--result", default="", help="an existing result folder to open at start (result.json + overlays)")
    p.add_argument("--out", help="folder the registrations are written into, one run-N folder each (default: a new temporary folder)")
    p.add_argument("--host", default=LOOPBACK, help="address to listen on (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"port (default {DEFAULT_PORT}; 0: any free port)")
    p.add_argument("--allow-remote", action="store_true", help="allow a --host other than the loopback address (a token is then required)")
    p.add_argument("--token", help="the token the page must present (default with --allow-remote: a random one, printed in the address)")
    registration_option_args(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    token = bind_token(args.host, args.allow_remote, args.token)
    options = options_from_args(args)
    for name, path in (("--case", args.case), ("--cta", args.cta), ("--dsa-pa", args.dsa_pa), ("--dsa-lat", args.dsa_lat),
                       ("--result", args.result)):
        if path and not Path(path).exists():
            raise InputError(f"{name} {path} does not exist: check the path")
    missing = [p for p in WEB_PACKAGES if importlib.util.find_spec(p) is None]
    if missing:
        raise InputError(f"geopose view needs the web extra ({', '.join(missing)} missing): pip install -e \".[web]\" "
                         "(or make setup)")
    from .app import serve
    from .session import Session

    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="geopose-view-"))
    fields = {"case_dir": args.case, "cta_file": args.cta, "pa_file": args.dsa_pa, "lat_file": args.dsa_lat,
              "result_dir": args.result}
    serve(args.host, args.port, token, Session(out), options, fields, open_result=bool(args.result), demo=args.demo)
    return 0
