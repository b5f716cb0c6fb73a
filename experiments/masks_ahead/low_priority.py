"""The demo phantom (geopose phantom --seed 20260 --out /tmp/prof/demo) registered twice with the mask thread at nice 19
(Linux keeps a priority per thread, and SimpleITK's Platform threader starts its threads from the calling one):
``python low_priority.py nice``, or ``plain`` for the code as committed."""
import os, sys, threading
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "Logic"))
import geopose
import torch
from geopose.render import volume as V
if sys.argv[1] == "nice":
    orig = V.RenderVolume._made
    def _made(self, name, source):
        if threading.current_thread().name == "geopose-cta-masks":
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)
        return orig(self, name, source)
    V.RenderVolume._made = _made
from geopose.cta.io import load_cta
from geopose.dsa.readers import read_dsa
from geopose.nets import load_models
from geopose.register.pipeline import register_case
torch.set_num_threads(2)
d = "/tmp/prof/demo"
cta = load_cta(f"{d}/cta.nii.gz"); runs = {"pa": read_dsa(f"{d}/dsa_pa.dcm"), "lat": read_dsa(f"{d}/dsa_lat.dcm")}
models = load_models(runtime="torch")
for _ in range(2):
    t = register_case(cta, runs, models=models).runtimes_s
    print(sys.argv[1], {k: round(v, 2) for k, v in t.items()}, "instant", round(t["calibration"] + t["init"] + t["refine"] + t["search"], 2), flush=True)
