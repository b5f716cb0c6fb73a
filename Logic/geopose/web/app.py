"""The page: inputs, Register / Cancel with a progress bar, the 3D view (trame-slicer: the networks' estimate as soon
as it is handed over, marked preliminary, then the result), each DSA view's overlay, the quality flags and the
stages, and saving. Needs the ``web`` extra.

All scene and VTK work runs on the server's event loop; the registration and the reading of a result
folder run in worker threads (:class:`~.session.Session`), and a ticker on the loop pushes their
progress to the page four times a second. The server listens before Slicer's MRML is imported: the
page is usable at once and its 3D view is attached when that import (in a thread) is done.
"""

from __future__ import annotations

import asyncio
import base64
import math
import os
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..register.report import OVERLAY_NAMES
from .session import Review, Session, error_line, files_from_fields, review_from_folder

#: Seconds between progress pushes while a worker runs.
TICK_S = 0.25
STAGE_TITLES = {"nominal": "DICOM angles", "init": "after Init", "refine": "after Refine", "search": "after search",
                "final": "final"}


def _import_slicer() -> None:
    """Import Slicer's MRML (the slicer-core wheel) and trame-slicer: seconds, so off the loop."""
    import trame_slicer.core  # noqa: F401
    import trame_slicer.rca_view  # noqa: F401


def _png_data_url(path: Path) -> str:
    return "data:image/png;base64," + base64.b64encode(path.read_bytes()).decode("ascii") if path.is_file() else ""


def _rotation_deg(a: np.ndarray, b: np.ndarray) -> float:
    r = np.asarray(a)[:3, :3].T @ np.asarray(b)[:3, :3]
    return math.degrees(math.acos(float(np.clip((np.trace(r) - 1) / 2, -1.0, 1.0))))


def quality_rows(record: dict) -> list[dict]:
    """Per view: its role, quality flag and reasons, final mNCC and silhouette Dice."""
    return [{"view": v.get("role", k.upper()), "flag": v["quality"]["flag"], "reasons": v["quality"]["reasons"],
             "mncc": f"{v['final_mncc']:.3f}", "dice": f"{v['silhouette_dice']:.3f}"} for k, v in record["views"].items()]


def stage_rows(record: dict) -> list[dict]:
    """Per view and stage: how far that stage's pose is from the final one (deg, source position mm)
    and, on a phantom, the carotid mPCD (mm) against the truth."""
    rows = []
    for key, v in record["views"].items():
        final = np.asarray(v["pose_centred"], dtype=float)
        truth = v.get("truth", {})
        for stage, entry in v["stages"].items():
            pose = np.asarray(entry["pose_centred"], dtype=float)
            mpcd = truth.get(stage, {}).get("mpcd_mm") if isinstance(truth.get(stage), dict) else None
            rows.append({"view": v.get("role", key.upper()), "stage": STAGE_TITLES.get(stage, stage),
                         "turn": f"{_rotation_deg(pose, final):.1f}", "shift": f"{np.linalg.norm(pose[:3, 3] - final[:3, 3]):.1f}",
                         "mpcd": "" if mpcd is None else f"{mpcd:.2f}"})
    return rows


class GeoPoseViewApp:
    """The trame app around one :class:`Session` and one trame-slicer ``SlicerApp``."""

    def __init__(self, server, session: Session, options, fields: dict[str, str]):
        from trame_client.widgets.core import VirtualNode

        self.server, self.session, self.options = server, session, options
        self.slicer_app = None
        self.views_node = VirtualNode(server)  # the 3D view's place in the page, filled by attach_views
        self._views_attached: asyncio.Future | None = None
        state = self.server.state
        state.trame__title = "GeoPose"
        state.update({"case_dir": "", "cta_file": "", "pa_file": "", "lat_file": "", "result_dir": "", **fields})
        state.update({"status": "idle", "error": "", "stage": "", "message": "", "fraction": 0.0, "elapsed": "",
                      "overlays": [], "quality": [], "stages": [], "saved": "", "result_folder": "",
                      "notes": [], "views_ready": False, "estimate": ""})
        self._build_ui()

    def attach_views(self) -> "asyncio.Future":
        """Import Slicer's MRML and trame-slicer in a thread, then build the Slicer app and its 3D view
        on the loop (once; the future is done when the view is in the page)."""
        if self._views_attached is None:
            self._views_attached = asyncio.ensure_future(self._attach_views())
        return self._views_attached

    async def _attach_views(self) -> None:
        await asyncio.get_running_loop().run_in_executor(None, _import_slicer)
        from trame_slicer.core import LayoutManager, SlicerApp
        from trame_slicer.rca_view import register_rca_factories

        self.slicer_app = SlicerApp()
        register_rca_factories(self.slicer_app.view_manager, self.server)
        layouts = LayoutManager(self.slicer_app.scene, self.slicer_app.view_manager, self.server,
                                virtual_node=self.views_node, is_virtual_node_initialized=True)
        layouts.register_layout_dict({"3D": LayoutManager.default_grid_configuration()["3D Only"]})
        with self.server.state:
            layouts.set_layout("3D")
            self.server.state.views_ready = True
        self.layout_manager = layouts

    # ------------------------------------------------------------------ actions
    def register(self) -> None:
        self.server.state.error = ""
        try:
            files = files_from_fields(self.server.state.case_dir, self.server.state.cta_file, self.server.state.pa_file,
                                      self.server.state.lat_file)
            self.session.start(files, self.options)
        except InputError as exc:
            self.server.state.error = error_line(exc)
            return
        self.server.state.status, self.server.state.estimate = "running", ""
        asyncio.ensure_future(self._follow_registration())

    async def demo_case(self) -> None:
        """Write the demo's phantom case (``geopose demo``'s, 1 mm) into the output folder, or reuse it,
        and fill the case field with it."""
        from ..demo import write_demo_case

        state = self.server.state
        case = self.session.out / "demo_case"
        if not (case / "vessels.nii.gz").is_file():
            with state:
                state.error, state.status, state.message = "", "loading", f"writing the demo phantom case into {case}..."
            try:
                await asyncio.get_running_loop().run_in_executor(None, write_demo_case, case)
            except Exception as exc:
                with state:
                    state.error, state.status, state.message = error_line(exc), "idle", ""
                return
        with state:
            state.case_dir, state.status, state.message = str(case), "idle", "demo case ready: press Register"

    def cancel(self) -> None:
        self.session.cancel()
        self.server.state.message = "cancelling at the next step..."

    async def _follow_registration(self) -> None:
        state = self.server.state
        shown = None
        while self.session.status == "running":
            p = self.session.progress
            with state:
                state.stage, state.message, state.fraction = p.stage, p.message[:90], round(100 * p.fraction, 1)
                state.elapsed = f"{self.session.elapsed_s():.1f} s"
            if self.session.estimate is not None and self.session.estimate is not shown:
                shown = self.session.estimate
                await self._show_estimate(shown)
            await asyncio.sleep(TICK_S)
        estimate, status = self.session.estimate, self.session.status
        kept = estimate is not None and status in ("cancelled", "error")  # the estimate stays in the 3D view
        if kept and estimate is not shown:
            await self._show_estimate(estimate)
        with state:
            state.status, state.error = status, self.session.error
            if status == "cancelled":
                state.message = "registration cancelled" + (": the 3D view keeps the networks' estimate" if kept else "")
            if kept:
                state.estimate = (f"preliminary: the networks' estimate ({estimate.preliminary.elapsed_s:.1f} s); "
                                  f"the registration did not finish ({status})")
            if status == "done":
                await self.attach_views()
                self._show(self.session.review, keep_camera=shown is not None)

    async def _show_estimate(self, estimate) -> None:
        """Show the networks' estimate of the running registration (a ``FileEstimate``) in the 3D view, marked
        preliminary, and clear the previous result's panels (its folder, overlays, flags and stages)."""
        from ..dsa import temporal_map
        from .scene import show_estimate

        maps = await asyncio.get_running_loop().run_in_executor(
            None, lambda: {key: temporal_map(run.frames) for key, run in estimate.runs.items()})
        await self.attach_views()
        state = self.server.state
        with state:
            show_estimate(self.slicer_app, estimate, maps)
            state.result_folder, state.overlays, state.quality, state.stages, state.notes, state.saved = "", [], [], [], [], ""
            state.estimate = (f"preliminary: the networks' estimate ({estimate.preliminary.elapsed_s:.1f} s), shown in the 3D view "
                              "while the registration refines it")

    async def open_result(self) -> None:
        state = self.server.state
        state.error = ""
        state.status = "loading"
        state.flush()
        try:
            review = await asyncio.get_running_loop().run_in_executor(None, review_from_folder, state.result_dir)
        except Exception as exc:
            state.error, state.status = error_line(exc), "idle"
            return
        await self.attach_views()
        with state:
            self._show(review)
            state.status = "done"

    def _show(self, review: Review, keep_camera: bool = False) -> None:
        from .scene import show_review

        state = self.server.state
        show_review(self.slicer_app, review, keep_camera)
        state.result_folder = str(review.folder)
        state.overlays = [{"name": n, "src": _png_data_url(review.folder / n)} for n in OVERLAY_NAMES]
        state.quality = quality_rows(review.record)
        state.stages = stage_rows(review.record)
        state.notes = list(review.record.get("notes", []))
        state.saved, state.estimate = "", ""

    def save_scene(self) -> None:
        from .scene import save_scene

        self._save(lambda folder: [save_scene(self.slicer_app, folder)])

    def save_transforms(self) -> None:
        from .scene import save_transforms

        self._save(lambda folder: save_transforms(self.slicer_app, folder))

    def _save(self, write) -> None:
        state = self.server.state
        state.error = ""
        try:
            if not state.result_folder or self.slicer_app is None:
                raise InputError("there is no result to save yet: register a case or open a result folder first")
            state.saved = "wrote " + ", ".join(str(p) for p in write(Path(state.result_folder)))
        except Exception as exc:
            state.error = error_line(exc)

    # ------------------------------------------------------------------ page
    def _build_ui(self) -> None:
        from trame.ui.vuetify3 import SinglePageWithDrawerLayout
        from trame.widgets import html
        from trame.widgets import vuetify3 as v3

        with SinglePageWithDrawerLayout(self.server, theme="dark") as layout:
            layout.title.set_text("GeoPose: CTA to biplane DSA")
            with layout.drawer as drawer:
                drawer.width = 420
                with html.Div(classes="pa-3 d-flex flex-column ga-2"):
                    html.Div("Case: a folder (cta.nii.gz, dsa_pa.dcm, dsa_lat.dcm) or the three files", classes="text-caption")
                    v3.VBtn("Demo case", click=self.demo_case, id="btn-demo", size="small", variant="tonal",
                            disabled=("status === 'running' || status === 'loading'",))
                    v3.VTextField(v_model=("case_dir",), label="case folder", density="compact", hide_details=True, id="field-case")
                    v3.VTextField(v_model=("cta_file",), label="CTA (file or DICOM folder)", density="compact", hide_details=True)
                    v3.VTextField(v_model=("pa_file",), label="PA DSA", density="compact", hide_details=True)
                    v3.VTextField(v_model=("lat_file",), label="lateral DSA", density="compact", hide_details=True)
                    with html.Div(classes="d-flex ga-2"):
                        v3.VBtn("Register", click=self.register, color="primary", id="btn-register",
                                disabled=("status === 'running' || status === 'loading'",))
                        v3.VBtn("Cancel", click=self.cancel, id="btn-cancel", disabled=("status !== 'running'",))
                    v3.VProgressLinear(model_value=("fraction",), height=18, color="primary", id="progress",
                                       v_show="status === 'running'")
                    html.Div("{{ stage }} {{ fraction }} % ({{ elapsed }}) {{ message }}", classes="text-caption",
                             id="progress-text", v_show="status === 'running' || message")
                    v3.VDivider()
                    v3.VTextField(v_model=("result_dir",), label="existing result folder", density="compact", hide_details=True,
                                  id="field-result")
                    v3.VBtn("Open result", click=self.open_result, id="btn-open",
                            disabled=("status === 'running' || status === 'loading'",))
                    v3.VAlert(text=("estimate",), type="info", density="compact", v_if="estimate", id="estimate")
                    v3.VAlert(text=("error",), type="error", density="compact", v_if="error", id="error")
                    html.Div("result: {{ result_folder }}", classes="text-caption", id="result-folder", v_if="result_folder")
                    v3.VDivider()
                    with html.Div(v_for="q in quality", key="q.view", classes="quality"):
                        with html.Div(classes="d-flex align-center ga-2"):
                            html.B("{{ q.view }}")
                            v3.VChip("{{ q.flag }}", color=("q.flag === 'ok' ? 'green' : (q.flag === 'doubtful' ? 'orange' : 'red')",),
                                     size="small", classes="quality-flag")
                            html.Span("mNCC {{ q.mncc }}, silhouette Dice {{ q.dice }}", classes="text-caption")
                        html.Div("{{ r }}", v_for="r in q.reasons", classes="text-caption quality-reason")
                    with v3.VTable(density="compact", v_if="stages.length", id="stages"):
                        with html.Thead():
                            with html.Tr():
                                for h in ("view", "stage", "turn to final (deg)", "source to final (mm)", "carotid mPCD (mm)"):
                                    html.Th(h)
                        with html.Tbody():
                            with html.Tr(v_for="s in stages"):
                                for k in ("view", "stage", "turn", "shift", "mpcd"):
                                    html.Td(f"{{{{ s.{k} }}}}")
                    html.Div("{{ n }}", v_for="n in notes", classes="text-caption")
                    with html.Div(classes="d-flex ga-2", v_if="result_folder"):
                        v3.VBtn("Save scene (.mrb)", click=self.save_scene, id="btn-save-scene", size="small")
                        v3.VBtn("Save transforms", click=self.save_transforms, id="btn-save-transforms", size="small")
                    html.Div("{{ saved }}", classes="text-caption", id="saved", v_if="saved")
            with layout.content:
                with html.Div(classes="d-flex", style="height: calc(100vh - 64px);"):
                    with html.Div(style="flex: 1.2 1 0; position: relative; min-width: 300px;", id="view3d"):
                        html.Div("3D view loading...", v_if="!views_ready", classes="pa-4 text-caption", id="views-loading")
                        self.views_node(layout)
                    with html.Div(classes="d-flex flex-column ga-1 pa-1", style="flex: 1 1 0; overflow-y: auto;", id="overlays"):
                        html.Img(v_for="o in overlays", key="o.name", src=("o.src",), alt=("o.name",),
                                 style="width: 100%; height: auto;", classes="overlay")


def serve(host: str, port: int, token: str | None, session: Session, options, fields: dict[str, str], open_result: bool,
          demo: bool = False) -> None:
    """Build the app and serve it until interrupted; prints the page's address once it listens."""
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    from trame.app import get_server
    from trame_rca import module as trame_rca_module
    from trame_slicer import module as trame_slicer_module

    from .access import page_url, token_middleware

    server = get_server("geopose", client_type="vue3")
    server.enable_module(trame_slicer_module)
    server.enable_module(trame_rca_module)
    app = GeoPoseViewApp(server, session, options, fields)
    if token:
        server.controller.on_server_bind.add(lambda web_server: web_server.app.middlewares.append(token_middleware(token)))

    def ready(**_):
        print(f"GeoPose view: open {page_url(host, server.port, token)}", flush=True)
        app.attach_views()
        if demo:
            asyncio.ensure_future(app.demo_case())
        if open_result:
            asyncio.ensure_future(app.open_result())

    server.controller.on_server_ready.add(ready)
    server.start(host=host, port=port, open_browser=False, show_connection_info=False, disable_logging=True, timeout=0)
