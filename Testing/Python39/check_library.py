"""Run under Python 3.9 with pydicom 2.4.4 (Slicer 5.8): the torch-free registration of a phantom
folder, the DICOM writer's round trip, and a byte-compile of the module's files. Prints one JSON object.

Usage: python check_library.py PHANTOM_FOLDER REPOSITORY
"""

import json
import py_compile
import sys
import tempfile
from pathlib import Path

folder, repo = Path(sys.argv[1]), Path(sys.argv[2])
sys.path.insert(0, str(repo / "Logic"))

import numpy as np  # noqa: E402
import pydicom  # noqa: E402

from geopose.cta import load_cta  # noqa: E402
from geopose.dsa import read_dsa, write_dsa_dicom  # noqa: E402
from geopose.register import register_case  # noqa: E402
from geopose.register.record import build_record  # noqa: E402

cta = load_cta(folder / "cta.nii.gz")
runs = {key: read_dsa(folder / f"dsa_{key}.dcm") for key in ("pa", "lat")}
record = build_record(register_case(cta, runs), runs)  # no PyTorch here: onnxruntime, TTO skipped
written = read_dsa(write_dsa_dicom(runs["pa"], folder / "written_pa.dcm"))
with tempfile.TemporaryDirectory() as tmp:
    for name in ("GeoPose", "GeoPoseTest"):
        py_compile.compile(str(repo / "GeoPoseModule" / f"{name}.py"), cfile=str(Path(tmp) / f"{name}.pyc"), doraise=True)
print(json.dumps({
    "python": list(sys.version_info[:2]),
    "pydicom": pydicom.__version__,
    "torch_loaded": "torch" in sys.modules,
    "engine": record["engine"]["backend"],
    "pose_centred": {key: record["views"][key]["pose_centred"] for key in runs},
    "written_frames_equal": bool(np.array_equal(written.frames, runs["pa"].frames)),
    "written_geometry_equal": written.angles == runs["pa"].angles and written.detector == runs["pa"].detector,
}))
