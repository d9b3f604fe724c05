"""Water on, water off in the viewer (the session's ``tiny_run`` checkpoint).

* the controls (``Water``, water density, veiling light, exposure, sRGB) and the display
  outputs of camera renders, through the model API;
* that they change neither training, nor the checkpoint, nor evaluation metrics (the
  pipeline's evaluations and nerfstudio's ``ns-eval``);
* the loopback default: nerfstudio's ``ns-viewer`` listens on ``0.0.0.0`` unless told, ours
  (``python -m seathru_nerfstudio.run_viewer``) on ``127.0.0.1`` unless told;
* the real viewer on the checkpoint, driven by headless chromium: it opens on ``rgb_display``,
  the Water control is shown, toggling it changes the rendered pixels, density 0 renders the
  clean image; and it listens on loopback only. The viewer and the browser run as soon as the
  tiny run is trained, beside the other tests (``TINY_RUN_JOBS``); the tests read what they saw.

Needs chromium (``apt-get install -y chromium``) and ``pip install playwright``.
"""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import tiny_checkpoint
import viewer_page

from seathru_nerfstudio.compat import load_checkpoint

CONTROL_LABELS = ("Water", "Water density", "Override veiling light", "Veiling light", "Exposure (stops)", "sRGB display")
LISTED_OUTPUTS = (
    "rgb_display", "clean_display", "direct_display", "backscatter_display", "water_split",
    "rgb", "clean", "direct", "backscatter", "depth", "accumulation",
    "medium_rgb", "medium_attenuation", "medium_backscatter", "medium_attenuation_display",
)  # fmt: skip
QUALITY_METRICS = ("psnr", "ssim", "clean_psnr", "clean_ssim", "depth_abs_rel")
MAX_RES = 64  # the viewer's smallest "Max res": cheap renders


def viewer_session(tiny_run: dict, folder: Path) -> dict:
    """Our loopback viewer entry point on the checkpoint (default host), and what the tests read
    of it: who listens (``hosts``), whether this machine's other interfaces refuse a connection
    (``others``), and what headless chromium did and saw on the page (``browser``, or the error
    that stopped it, ``browser_error``). Listed in ``TINY_RUN_JOBS``: the suite runs it as soon as
    the tiny run is trained (conftest's ``background_job``); the viewer stops at its end."""
    import psutil

    port = viewer_page.free_port()
    with open(folder / "viewer.log", "w") as log:
        proc = tiny_checkpoint.start_group(
            [
                sys.executable, "-m", "seathru_nerfstudio.run_viewer",
                "--load-config", tiny_run["config"],
                "--viewer.websocket-port", port,
                "--viewer.image-format", "png",  # lossless: pixel comparisons
                "--viewer.max-num-display-images", 0,  # no camera thumbnails over the render: they load
                # asynchronously and changed the measured pixels between captures (two exact states seen)
            ],
            env=tiny_checkpoint.quiet_env(),
            stdout=log,
            stderr=subprocess.STDOUT,
        )  # fmt: skip
    try:
        viewer_page.wait_for_port(port, proc)
        session = {"hosts": listening_hosts(proc.pid, port), "others": {}}
        addresses = [
            a.address
            for addrs in psutil.net_if_addrs().values()
            for a in addrs
            if a.family == socket.AF_INET and not a.address.startswith("127.")
        ]
        for address in addresses:  # this machine's other interfaces: nobody should answer there
            try:
                socket.create_connection((address, port), timeout=2).close()
                session["others"][address] = "answered"
            except OSError as error:
                session["others"][address] = f"refused: {error}"
        try:
            session["browser"] = drive_browser(f"http://127.0.0.1:{port}", folder)
        except Exception as error:  # noqa: BLE001 - the browser test raises it; the loopback one does not need it
            session["browser_error"] = error
        return session
    finally:
        tiny_checkpoint.stop_group(proc)


TINY_RUN_JOBS = [viewer_session]


@pytest.fixture(scope="module")
def pipeline(tiny_pipeline):
    """The session's pipeline, one math thread."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    tiny_pipeline.eval()
    yield tiny_pipeline
    torch.set_num_threads(threads)


@pytest.fixture
def controls(pipeline):
    """The model's viewer controls, back to their defaults after the test."""
    from nerfstudio.viewer.viewer_elements import ViewerParameter

    ctrl = pipeline.model.viewer_controls
    elements = [v for v in vars(ctrl).values() if isinstance(v, ViewerParameter)]
    defaults = [e.value for e in elements]
    yield ctrl
    for element, value in zip(elements, defaults):
        element.value = value


def extreme(ctrl) -> None:
    """Every control away from its default."""
    ctrl.c1_water.value = False
    ctrl.c2_density.value = 0.0
    ctrl.c3_veil_override.value = True
    ctrl.c4_veil_rgb.value = (255, 0, 0)
    ctrl.c5_exposure.value = 3.0
    ctrl.c6_srgb.value = False


def render(pipeline, camera):
    """A camera render as the viewer and ns-render get it (nerfstudio's evaluation methods
    leave the pipeline in train mode, hence the eval())."""
    pipeline.eval()
    return pipeline.model.get_outputs_for_camera(camera)


def eval_camera(pipeline, index: int = 0):
    return pipeline.datamanager.eval_dataset.cameras[index : index + 1].to(pipeline.device)


def listening_hosts(pid: int, port: int) -> set:
    import psutil

    procs = [psutil.Process(pid)]
    procs += procs[0].children(recursive=True)
    hosts = set()
    for proc in procs:
        for conn in proc.net_connections(kind="inet"):
            if conn.status == psutil.CONN_LISTEN and conn.laddr.port == port:
                hosts.add(conn.laddr.ip)
    return hosts


# --- the controls and the display outputs, through the model ------------------------------------


def test_controls_are_viewer_elements_in_their_folder_and_hold_no_state(pipeline, tiny_run):
    from nerfstudio.viewer.utils import parse_object
    from nerfstudio.viewer.viewer_elements import ViewerElement

    found = {element.name: path for path, element in parse_object(pipeline, ViewerElement, "Custom Elements")}
    for label in CONTROL_LABELS:
        assert found.get(label, "").startswith("Custom Elements/seathru/"), (label, found)
    assert pipeline.model.viewer_controls.c6_srgb.value is True  # linear data: sRGB display by default

    # Nothing of the viewer is in the state dict: the checkpoint has exactly the same keys.
    (ckpt_path,) = list((tiny_run["config"].parent / "nerfstudio_models").glob("*.ckpt"))
    saved = load_checkpoint(ckpt_path)["pipeline"]
    assert set(saved) == set(pipeline.state_dict())
    assert not [k for k in saved if "viewer" in k or k.startswith("seathru.")]


def test_display_outputs_water_toggle_density_veil_exposure(pipeline, controls):
    from seathru_nerfstudio.colour import linear_to_srgb
    from seathru_nerfstudio.viewer import DENSITY_OUTPUTS, DISPLAY_OUTPUTS

    cam = eval_camera(pipeline)
    base = render(pipeline, cam)
    assert tuple(base)[: len(DISPLAY_OUTPUTS)] == DISPLAY_OUTPUTS  # first: the viewer opens on rgb_display
    for name in LISTED_OUTPUTS + ("expected_depth", "prop_depth_0", "prop_depth_1"):
        assert name in base, name

    # sRGB display of linear radiance (so linear data does not look dark), all in [0, 1].
    for name in ("rgb", "clean", "direct", "backscatter", "medium_rgb"):
        torch.testing.assert_close(base[name + "_display"], linear_to_srgb(base[name]), atol=1e-6, rtol=0)
    assert float(base["rgb_display"].mean()) > float(base["rgb"].mean()) + 0.05
    for name in DENSITY_OUTPUTS:  # densities per scene unit, shown relative to their maximum
        shown = base[name + "_display"]
        assert float(shown.min()) >= 0.0 and abs(float(shown.max()) - 1.0) < 1e-6
        torch.testing.assert_close(shown, base[name] / base[name].max(), atol=1e-6, rtol=0)
    half = base["rgb"].shape[1] // 2
    torch.testing.assert_close(base["water_split"][:, :half], base["rgb_display"][:, :half])
    torch.testing.assert_close(base["water_split"][:, half + 1 :], base["clean_display"][:, half + 1 :])

    # Water off: rgb_display is the clean image; rgb itself is still the image in the water.
    controls.c1_water.value = False
    off = render(pipeline, cam)
    assert torch.equal(off["rgb_display"], off["clean_display"])
    assert float((off["rgb_display"] - base["rgb_display"]).abs().mean()) > 0.02
    assert torch.equal(off["rgb"], base["rgb"])
    controls.c1_water.value = True

    # Density 0: no water at all, rgb == clean, no backscatter.
    controls.c2_density.value = 0.0
    clear = render(pipeline, cam)
    assert float((clear["rgb"] - clear["clean"]).abs().max()) < 1e-5
    assert float(clear["backscatter"].abs().max()) == 0.0
    assert float(clear["medium_attenuation"].abs().max()) == 0.0

    # Three times the density: more backscatter.
    controls.c2_density.value = 3.0
    dense = render(pipeline, cam)
    assert float(dense["backscatter"].mean()) > float(base["backscatter"].mean()) + 1e-3
    torch.testing.assert_close(dense["medium_backscatter"], 3 * base["medium_backscatter"])
    controls.c2_density.value = 1.0

    # Veiling light pure red: c_med red, backscatter red only.
    controls.c3_veil_override.value = True
    controls.c4_veil_rgb.value = (255, 0, 0)
    red = render(pipeline, cam)
    torch.testing.assert_close(red["medium_rgb"], torch.tensor([1.0, 0.0, 0.0]).expand_as(red["medium_rgb"]))
    assert float(red["backscatter"][..., 1:].abs().max()) == 0.0
    assert float(red["backscatter"][..., 0].mean()) > 0.0
    controls.c3_veil_override.value = False

    # Exposure +1 stop, sRGB off: display = clamp(2 * linear).
    controls.c5_exposure.value = 1.0
    controls.c6_srgb.value = False
    bright = render(pipeline, cam)
    torch.testing.assert_close(bright["clean_display"], (2 * base["clean"]).clamp(0, 1), atol=1e-6, rtol=0)


def test_controls_change_neither_training_nor_the_state_dict(pipeline, controls):
    model, cam = pipeline.model, eval_camera(pipeline)
    rays = cam.generate_rays(camera_indices=0).flatten()[:96]
    image = pipeline.datamanager.eval_dataset[0]["image"][..., :3].reshape(-1, 3)[:96]
    batch = {"image": image}
    state = {k: v.clone() for k, v in model.state_dict().items()}

    def train_step():
        model.train()
        try:
            torch.manual_seed(0)
            outputs = model(rays)
            metrics = model.get_metrics_dict(outputs, batch)
            losses = model.get_loss_dict(outputs, batch, metrics)
            return outputs, losses
        finally:
            model.eval()

    reference = train_step()
    extreme(controls)
    render(pipeline, cam)  # a viewer render with every control away from its default, in between
    changed = train_step()
    for ref, new in zip(reference, changed):
        for key, value in ref.items():
            if isinstance(value, torch.Tensor):
                assert torch.equal(value, new[key]), key
    for key, value in model.state_dict().items():
        assert torch.equal(value, state[key]), key


def test_evaluation_metrics_ignore_the_controls_and_match_ns_eval(pipeline, controls, ns_eval_results):
    from seathru_nerfstudio import metrics

    def quality(d):
        return {k: d[k] for k in QUALITY_METRICS}

    reference = quality(pipeline.get_average_eval_image_metrics())
    for key in QUALITY_METRICS:  # nerfstudio's ns-eval CLI reports the same (linear) metrics
        assert abs(ns_eval_results[key] - reference[key]) < 1e-4, (key, ns_eval_results[key], reference[key])

    extreme(controls)
    assert quality(pipeline.get_average_eval_image_metrics()) == reference  # the controls never reach them
    single, _ = pipeline.get_eval_image_metrics_and_images(step=0)
    assert np.isfinite(single["psnr"])
    _, eval_losses, _ = pipeline.get_eval_loss_dict(step=0)
    assert all(torch.isfinite(v) for v in eval_losses.values())
    assert pipeline.model.medium_controls_enabled  # back on after each evaluation

    # Outside evaluation the same controls do change the render (density 0: no water) ...
    camera, batch = next(iter(pipeline.datamanager.fixed_indices_eval_dataloader))
    clear = render(pipeline, camera)
    torch.testing.assert_close(clear["rgb"], clear["clean"], atol=1e-5, rtol=0)
    # ... and the metrics are of the outputs given: the linear ones, never the display ones.
    controls.c2_density.value, controls.c3_veil_override.value = 1.0, False  # the trained water again
    plain = render(pipeline, camera)
    gt = batch["image"][..., :3].to(pipeline.device)
    scores, _ = pipeline.model.get_image_metrics_and_images(plain, batch)
    assert scores["psnr"] == pytest.approx(metrics.psnr(plain["rgb"].clamp(0, 1), gt))
    assert abs(scores["psnr"] - metrics.psnr(plain["rgb_display"], gt)) > 1.0


# --- the network: who can reach the viewer ------------------------------------------------------


def test_ns_viewer_defaults_to_every_interface_and_ours_to_loopback():
    """nerfstudio's ns-viewer ignores the host saved with a run (docs/viewer.md says so); our
    entry point is the same command listening on 127.0.0.1 unless --viewer.websocket-host is given."""
    import tyro
    from nerfstudio.scripts.viewer.run_viewer import RunViewer

    from seathru_nerfstudio.run_viewer import RunLoopbackViewer

    def parse(cls, *args):
        return tyro.cli(tyro.conf.FlagConversionOff[cls], args=["--load-config", "c.yml", *args])

    assert parse(RunViewer).viewer.websocket_host == "0.0.0.0"
    ours = parse(RunLoopbackViewer)
    assert ours.viewer.websocket_host == "127.0.0.1" and ours.load_config == Path("c.yml")
    assert ours.viewer.as_viewer_config().websocket_host == "127.0.0.1"  # what the Viewer is built with
    assert parse(RunLoopbackViewer, "--viewer.websocket-host", "0.0.0.0").viewer.websocket_host == "0.0.0.0"


@pytest.mark.slow  # reads a TINY_RUN_JOBS result: the tiny run is trained for it
def test_our_viewer_listens_on_loopback_only(background_job):
    session = background_job(viewer_session)
    assert session["hosts"] == {"127.0.0.1"}
    assert all(outcome.startswith("refused") for outcome in session["others"].values()), session["others"]


# --- the real viewer in a browser ---------------------------------------------------------------


def drive_browser(url: str, folder: Path) -> dict:
    """Open the viewer at ``url`` in headless chromium, toggle the water off and on, take the water
    density to 0, and record what the page showed and what it was sent (screenshots in ``folder``).
    Its assertions stop the session where a later step would only wait for a render that cannot come."""
    assert viewer_page.chromium_path(), "needs chromium (apt-get install -y chromium)"
    measured, sent = {}, {}
    with viewer_page.browser_page() as page:
        view = viewer_page.ViewerPage(page, url)
        view.open()
        view.wait_for_label("Water")
        for label in CONTROL_LABELS:
            assert view.has_control(label), label
        assert view.slider_to_min("Max res") == MAX_RES

        water = view.wait_for_render(MAX_RES)
        sent["water"] = view.last_received(MAX_RES)
        page.screenshot(path=str(folder / "1-water.png"))
        assert view.dropdown_value("Output type") == "rgb_display"
        options = view.dropdown_options("Output type")
        assert set(LISTED_OUTPUTS) <= set(options), options

        assert view.click_checkbox("Water") is False
        no_water = view.wait_for_render(MAX_RES, previous=water)
        sent["no_water"] = view.last_received(MAX_RES)
        page.screenshot(path=str(folder / "2-no-water.png"))
        measured["resolution_no_water"] = view.resolution()
        measured["water_vs_no_water"] = viewer_page.mean_abs_diff(water, no_water)

        assert view.click_checkbox("Water") is True
        water_again = view.wait_for_render(MAX_RES, previous=no_water)
        sent["water_again"] = view.last_received(MAX_RES)
        measured["water_vs_water_again"] = viewer_page.mean_abs_diff(water, water_again)

        assert view.slider_to_min("Water density") == 0.0
        clear = view.wait_for_render(MAX_RES, previous=water_again)
        sent["density0"] = view.last_received(MAX_RES)
        page.screenshot(path=str(folder / "3-density-0.png"))
        measured["resolution_at_density0"] = view.resolution()
        measured["density0_vs_no_water"] = viewer_page.mean_abs_diff(clear, no_water)
        measured["density0_vs_water"] = viewer_page.mean_abs_diff(clear, water_again)
        measured["images_received"] = len(view.received)
    return {"measured": measured, "sent": sent}


@pytest.mark.slow  # reads a TINY_RUN_JOBS result: the tiny run is trained for it
def test_browser_water_toggle_changes_pixels_and_density_zero_is_clean(background_job, tmp_path):
    session = background_job(viewer_session)
    if "browser_error" in session:
        raise session["browser_error"]  # an assertion of the session's, or what stopped it
    measured, sent = session["browser"]["measured"], session["browser"]["sent"]

    sent_diff = {f"sent_{a}_vs_{b}": viewer_page.mean_abs_diff(sent[a], sent[b]) for a, b in (("water", "water_again"), ("density0", "no_water"), ("water", "no_water"))}
    (tmp_path / "measured.json").write_text(json.dumps({**measured, **sent_diff}, indent=2))
    print("viewer pixel differences (mean abs, 0-255):", measured, sent_diff)
    # what the browser was sent: the same render again, bit for bit
    assert np.array_equal(sent["water_again"], sent["water"]), sent_diff  # the toggle goes back
    assert np.array_equal(sent["density0"], sent["no_water"]), sent_diff  # no water: rgb is the clean image
    assert sent_diff["sent_water_vs_no_water"] > 5.0
    # what the user sees: the canvas changes with the toggle and the slider. One received image
    # shows with up to 1.9 levels of difference between captures, so "the same" is judged against
    # the change the water makes.
    assert measured["water_vs_no_water"] > 5.0
    assert measured["density0_vs_water"] > 5.0
    assert measured["water_vs_water_again"] < 0.2 * measured["water_vs_no_water"]
    assert measured["density0_vs_no_water"] < 0.2 * measured["density0_vs_water"]
