"""One registration of the demo phantom with torch imported before geopose (its idle OpenMP threads spin under
OMP_WAIT_POLICY=ACTIVE): ``OMP_WAIT_POLICY=ACTIVE python spinning_threads.py REPO`` with REPO a checkout (its Logic/ is
imported). The demo phantom is ``geopose phantom --seed 20260 --out /tmp/prof/demo``; prints the stage times twice."""
import sys, time
import torch  # before geopose: idle OpenMP threads spin under OMP_WAIT_POLICY=ACTIVE
sys.path.insert(0, sys.argv[1] + "/Logic")
import geopose
from geopose.cta.io import load_cta
from geopose.dsa.readers import read_dsa
from geopose.nets import load_models
from geopose.register.pipeline import register_case
torch.set_num_threads(2)
d = "/tmp/prof/demo"
cta = load_cta(f"{d}/cta.nii.gz"); runs = {"pa": read_dsa(f"{d}/dsa_pa.dcm"), "lat": read_dsa(f"{d}/dsa_lat.dcm")}
models = load_models(runtime="torch")
for _ in range(2):
    r = register_case(cta, runs, models=models)
    t = r.runtimes_s
    print(geopose.__file__.split("/")[3], {k: round(v, 2) for k, v in t.items()}, flush=True)
