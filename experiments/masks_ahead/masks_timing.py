"""When should the CTA's masks be made? Variants on the same cases, one process, models loaded once:
ahead (the product: from prepare on), after (started once the networks' estimate is handed over), sitk1 (from prepare
on, SimpleITK at one thread while the masks are made). Per run: the time the estimate was shown and the total (s).

    .venv/bin/python experiments/masks_ahead/masks_timing.py CASE_FOLDER...   (geopose phantom folders)"""
import sys, json, time
sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[2] / "Logic"))
import geopose
import torch; torch.set_num_threads(2)
import SimpleITK as sitk
from geopose.cta import load_cta
from geopose.dsa import read_dsa
from geopose.nets import load_models
from geopose.register import register_case
from geopose.render.volume import RenderVolume
models = load_models()
real_ahead, real_made = RenderVolume.make_masks_ahead, RenderVolume._made
def run(d, variant):
    cta = load_cta(f"{d}/cta.nii.gz"); runs = {k: read_dsa(f"{d}/dsa_{k}.dcm") for k in ("pa", "lat")}
    held, shown = [], []
    RenderVolume.make_masks_ahead, RenderVolume._made = real_ahead, real_made
    if variant == "after":
        RenderVolume.make_masks_ahead = lambda self: held.append(self)
    if variant == "sitk1":
        def made(self, name, source):
            sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(1)
            try:
                return real_made(self, name, source)
            finally:
                sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(2)
        RenderVolume._made = made
    def prelim(p):
        shown.append(p.elapsed_s)
        for v in held:
            real_ahead(v)
    r = register_case(cta, runs, models=models, preliminary=prelim)
    return {"case": d.split("/")[-1], "variant": variant, "shown": round(shown[0], 2), "total": round(r.runtimes_s["total"], 2),
            "refine": round(r.runtimes_s["refine"], 2), "tto": round(r.runtimes_s["tto"], 2),
            "pose": r.views["pa"].final_pose.tolist()}  # compared between the variants
cases = sys.argv[1:]
run(cases[0], "ahead")  # warm-up
for d in cases:
    for variant in ("ahead", "after", "sitk1", "ahead", "after", "sitk1"):
        rec = run(d, variant)
        print(json.dumps({k: v for k, v in rec.items() if k != "pose"}), flush=True)
        with open(str(__import__("pathlib").Path(__file__).with_suffix(".jsonl")), "a") as f:
            f.write(json.dumps(rec) + "\n")
