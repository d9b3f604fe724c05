"""Issue #4, water on / water off, in the viewer.

* the controls (``Water``, water density, veiling light, exposure, sRGB) and the display
  transform of camera renders, through the model API;
* that they change neither training, nor the checkpoint, nor evaluation metrics (the
  pipeline's evaluation and nerfstudio's ``ns-eval`` code);
* the real ``ns-viewer`` on a trained checkpoint, driven by headless chromium: the Water
  control is shown, toggling it changes the rendered pixels, density 0 renders ``rgb`` as
  the clean image;
* the viewer listens on loopback only unless ``--viewer.websocket-host`` opts in.

One tiny checkpoint for the module (``tests/browser/tiny_checkpoint.py``). Needs chromium
(``apt-get install -y chromium``) and ``pip install playwright``.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent / "browser"))
import tiny_checkpoint  # noqa: E402
import viewer_page  # noqa: E402

pytestmark = pytest.mark.slow

CONTROL_LABELS = ("Water", "Water density", "Override veiling light", "Veiling light", "Exposure (stops)", "sRGB display")
LISTED_OUTPUTS = (
    "rgb", "clean", "direct", "backscatter", "depth", "accumulation",
    "medium_rgb", "medium_attenuation", "medium_backscatter", "water_split",
)  # fmt: skip
QUALITY_METRICS = ("psnr", "ssim", "clean_psnr", "clean_ssim", "depth_abs_rel")
MAX_RES = 64  # the viewer's smallest "Max res": cheap renders


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    return tiny_checkpoint.train_tiny(tmp_path_factory.mktemp("viewer"))


@pytest.fixture(scope="module")
def viewer_process(trained):
    """The real ``ns-viewer`` on the checkpoint, default host. Started by the first test so it
    boots while the in-process tests run; stopped at the end of the module."""
    port = viewer_page.free_port()
    log_path = trained["root"] / "ns-viewer.log"
    with open(log_path, "w") as log:
        proc = tiny_checkpoint.start_group(
            [
                tiny_checkpoint.BIN / "ns-viewer",
                "--load-config", trained["config"],
                "--viewer.websocket-port", port,
                "--viewer.image-format", "png",  # lossless: pixel comparisons
                "--viewer.max-num-display-images", 8,
            ],
            env=tiny_checkpoint.quiet_env(),
            stdout=log,
            stderr=subprocess.STDOUT,
        )  # fmt: skip
    yield {"proc": proc, "port": port, "log": log_path}
    tiny_checkpoint.stop_group(proc)


@pytest.fixture(scope="module")
def pipeline(trained, viewer_process):
    from nerfstudio.utils.eval_utils import eval_setup

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    _, pipe, _, _ = eval_setup(trained["config"], test_mode="test")
    yield pipe
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


def show(pipeline, camera):
    """A display render, as the viewer and ns-render get."""
    from seathru_nerfstudio import viewer

    pipeline.eval()  # nerfstudio's evaluation methods leave the pipeline in train mode
    with viewer.display_renders():
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


# --- the controls and the display transform, through the model ---------------------------------


def test_controls_are_viewer_elements_in_their_folder_and_hold_no_state(pipeline, trained):
    from nerfstudio.viewer.utils import parse_object
    from nerfstudio.viewer.viewer_elements import ViewerElement

    found = {element.name: path for path, element in parse_object(pipeline, ViewerElement, "Custom Elements")}
    for label in CONTROL_LABELS:
        assert found.get(label, "").startswith("Custom Elements/seathru/"), (label, found)
    assert pipeline.model.viewer_controls.c6_srgb.value is True  # linear data: sRGB display by default

    # Nothing of the viewer is in the state dict: the checkpoint has exactly the same keys.
    (ckpt_path,) = list((trained["config"].parent / "nerfstudio_models").glob("*.ckpt"))
    saved = torch.load(ckpt_path, map_location="cpu")["pipeline"]
    assert set(saved) == set(pipeline.state_dict())
    assert not [k for k in saved if "viewer" in k or k.startswith("seathru.")]


def test_display_render_water_toggle_density_veil_exposure(pipeline, controls):
    from seathru_nerfstudio.viewer import DENSITY_OUTPUTS, DisplayOutputs, linear_to_srgb

    model, cam = pipeline.model, eval_camera(pipeline)
    base = show(pipeline, cam)
    assert isinstance(base, DisplayOutputs)
    lin = base.linear
    for name in LISTED_OUTPUTS + ("expected_depth", "prop_depth_0", "prop_depth_1"):
        assert name in base, name

    # sRGB display of linear radiance (so linear data does not look dark), all in [0, 1].
    for name in ("rgb", "clean", "direct", "backscatter", "medium_rgb"):
        torch.testing.assert_close(base[name], linear_to_srgb(lin[name]), atol=1e-6, rtol=0)
    assert float(base["rgb"].mean()) > float(lin["rgb"].mean()) + 0.05
    for name in DENSITY_OUTPUTS:  # densities per scene unit, shown relative to their maximum
        assert float(base[name].min()) >= 0.0 and abs(float(base[name].max()) - 1.0) < 1e-6
        torch.testing.assert_close(base[name], lin[name] / lin[name].max(), atol=1e-6, rtol=0)
    half = base["rgb"].shape[1] // 2
    torch.testing.assert_close(base["water_split"][:, :half], base["rgb"][:, :half])
    torch.testing.assert_close(base["water_split"][:, half + 1 :], base["clean"][:, half + 1 :])
    # Depth and accumulation are left to nerfstudio's colormaps.
    for name in ("depth", "accumulation"):
        assert torch.equal(base[name], lin[name])

    # Water off: rgb is the clean image.
    controls.c1_water.value = False
    off = show(pipeline, cam)
    assert torch.equal(off["rgb"], off["clean"])
    assert float((off["rgb"] - base["rgb"]).abs().mean()) > 0.02
    controls.c1_water.value = True

    # Density 0: no water at all, rgb == clean, no backscatter.
    controls.c2_density.value = 0.0
    clear = show(pipeline, cam)
    assert float((clear.linear["rgb"] - clear.linear["clean"]).abs().max()) < 1e-5
    assert float((clear["rgb"] - clear["clean"]).abs().max()) < 1e-4
    assert float(clear.linear["backscatter"].abs().max()) == 0.0
    assert float(clear.linear["medium_attenuation"].abs().max()) == 0.0

    # Three times the density: more backscatter.
    controls.c2_density.value = 3.0
    dense = show(pipeline, cam)
    assert float(dense.linear["backscatter"].mean()) > float(lin["backscatter"].mean()) + 1e-3
    torch.testing.assert_close(dense.linear["medium_backscatter"], 3 * lin["medium_backscatter"])
    controls.c2_density.value = 1.0

    # Veiling light pure red: c_med red, backscatter red only.
    controls.c3_veil_override.value = True
    controls.c4_veil_rgb.value = (255, 0, 0)
    red = show(pipeline, cam)
    torch.testing.assert_close(red["medium_rgb"], torch.tensor([1.0, 0.0, 0.0]).expand_as(red["medium_rgb"]))
    assert float(red.linear["backscatter"][..., 1:].abs().max()) == 0.0
    assert float(red.linear["backscatter"][..., 0].mean()) > 0.0
    controls.c3_veil_override.value = False

    # Exposure +1 stop, sRGB off: display = clamp(2 * linear).
    controls.c5_exposure.value = 1.0
    controls.c6_srgb.value = False
    bright = show(pipeline, cam)
    torch.testing.assert_close(bright["clean"], (2 * lin["clean"]).clamp(0, 1), atol=1e-6, rtol=0)


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
            model.eval()
            with torch.no_grad():
                eval_forward = model(rays)  # a forward pass outside a camera render
            return outputs, losses, eval_forward
        finally:
            model.eval()

    reference = train_step()
    extreme(controls)
    show(pipeline, cam)  # a display render with every override on, in between
    changed = train_step()
    for ref, new in zip(reference, changed):
        for key, value in ref.items():
            if isinstance(value, torch.Tensor):
                assert torch.equal(value, new[key]), key
    for key, value in model.state_dict().items():
        assert torch.equal(value, state[key]), key


def test_evaluation_metrics_are_on_linear_outputs(pipeline, controls, trained, tmp_path):
    from nerfstudio.scripts.eval import ComputePSNR

    from seathru_nerfstudio import metrics, viewer

    def quality(d):
        return {k: d[k] for k in QUALITY_METRICS}

    reference = quality(pipeline.get_average_eval_image_metrics())
    extreme(controls)
    with viewer.display_renders():  # as if the viewer's thread evaluated: still linear
        overridden = quality(pipeline.get_average_eval_image_metrics())
    single, _ = pipeline.get_eval_image_metrics_and_images(step=0)
    assert overridden == reference  # the viewer's controls never reach the metrics
    assert np.isfinite(single["psnr"])

    # They are the metrics of the linear outputs, not of what a display render shows.
    controls.c1_water.value, controls.c2_density.value = True, 1.0
    controls.c3_veil_override.value, controls.c5_exposure.value, controls.c6_srgb.value = False, 0.0, True
    camera, batch = next(iter(pipeline.datamanager.fixed_indices_eval_dataloader))
    shown = show(pipeline, camera)
    with viewer.display_renders(), viewer.linear_outputs():  # linear_outputs wins
        linear = pipeline.model.get_outputs_for_camera(camera)
    assert not isinstance(linear, viewer.DisplayOutputs)
    # Any other caller (ns-eval, benchmarks, scripts) gets the linear outputs too.
    plain = pipeline.model.get_outputs_for_camera(camera)
    assert not isinstance(plain, viewer.DisplayOutputs) and "water_split" not in plain
    assert torch.equal(plain["rgb"], linear["rgb"])
    gt = batch["image"][..., :3].to(pipeline.device)
    linear_psnr = metrics.psnr(linear["rgb"].clamp(0, 1), gt)
    display_psnr = metrics.psnr(shown["rgb"], gt)
    assert abs(linear_psnr - display_psnr) > 1.0
    # The model's metrics on a display render fall back to its linear outputs...
    from_display, _ = pipeline.model.get_image_metrics_and_images(shown, batch)
    assert abs(from_display["psnr"] - linear_psnr) < 1e-4
    # ... unless the viewer changed the water, then they refuse.
    controls.c2_density.value = 0.0
    with pytest.raises(RuntimeError, match="linear_outputs"):
        pipeline.model.get_image_metrics_and_images(show(pipeline, camera), batch)

    # nerfstudio's ns-eval (its ComputePSNR, in-process) reports the linear metrics too.
    output = tmp_path / "eval.json"
    ComputePSNR(load_config=trained["config"], output_path=output).main()
    results = json.loads(output.read_text())["results"]
    for key in QUALITY_METRICS:
        assert abs(results[key] - reference[key]) < 1e-4, (key, results[key], reference[key])


def test_viewer_opt_in_to_other_interfaces_from_the_command_line(pipeline, trained, tmp_path, monkeypatch):
    """In-process nerfstudio Viewer (what ns-viewer and ns-train build) given nerfstudio's own
    default host 0.0.0.0, as ns-viewer passes it: with --viewer.websocket-host on the command
    line it listens there (without it, loopback: test_ns_viewer_listens_on_loopback_only)."""
    from nerfstudio.configs.base_config import ViewerConfig
    from nerfstudio.viewer.utils import parse_object
    from nerfstudio.viewer.viewer import Viewer
    from nerfstudio.viewer.viewer_elements import ViewerElement

    from seathru_nerfstudio.viewer import host_on_command_line, install_loopback_default

    assert host_on_command_line(["--viewer.websocket-host", "0.0.0.0"])
    assert host_on_command_line(["--load-config", "c.yml", "--viewer.websocket_host=0.0.0.0"])
    assert not host_on_command_line(["--load-config", "c.yml", "--viewer.websocket-port", "7007"])

    install_loopback_default()  # idempotent; ns-viewer and ns-train have it from the model
    monkeypatch.setattr(sys, "argv", ["ns-viewer", "--viewer.websocket-host", "0.0.0.0"])
    port = viewer_page.free_port()
    config = ViewerConfig(websocket_host="0.0.0.0", websocket_port=port)
    viewer = Viewer(config, log_filename=tmp_path / "viewer_log.txt", datapath=trained["scene"], pipeline=pipeline)
    try:
        assert listening_hosts(os.getpid(), port) == {"0.0.0.0"}
    finally:
        viewer.viser_server.stop()
        for _, element in parse_object(pipeline, ViewerElement, "Custom Elements"):
            element.gui_handle = None  # detach from the stopped server: defaults again


# --- the real ns-viewer --------------------------------------------------------------------------


def test_ns_viewer_listens_on_loopback_only(viewer_process):
    import psutil

    viewer_page.wait_for_port(viewer_process["port"], viewer_process["proc"])
    assert listening_hosts(viewer_process["proc"].pid, viewer_process["port"]) == {"127.0.0.1"}
    others = [
        a.address
        for addrs in psutil.net_if_addrs().values()
        for a in addrs
        if a.family == socket.AF_INET and not a.address.startswith("127.")
    ]
    for address in others:  # this machine's other interfaces: nobody answers there
        with pytest.raises(OSError):
            socket.create_connection((address, viewer_process["port"]), timeout=2).close()


@pytest.mark.skipif(viewer_page.chromium_path() is None, reason="needs chromium (apt-get install -y chromium)")
def test_browser_water_toggle_changes_pixels_and_density_zero_is_clean(viewer_process, tmp_path):
    pytest.importorskip("playwright")
    viewer_page.wait_for_port(viewer_process["port"], viewer_process["proc"])
    measured = {}
    with viewer_page.browser_page() as page:
        view = viewer_page.ViewerPage(page, f"http://127.0.0.1:{viewer_process['port']}")
        view.open()
        view.wait_for_label("Water")
        for label in CONTROL_LABELS:
            assert view.has_control(label), label
        assert view.slider_to_min("Max res") == MAX_RES

        water = view.wait_for_render(MAX_RES)
        page.screenshot(path=str(tmp_path / "1-water.png"))
        options = view.dropdown_options("Output type")
        assert set(LISTED_OUTPUTS) <= set(options), options

        assert view.click_checkbox("Water") is False
        no_water = view.wait_for_render(MAX_RES, previous=water)
        page.screenshot(path=str(tmp_path / "2-no-water.png"))
        measured["water_vs_no_water"] = viewer_page.mean_abs_diff(water, no_water)

        assert view.click_checkbox("Water") is True
        water_again = view.wait_for_render(MAX_RES, previous=no_water)
        measured["water_vs_water_again"] = viewer_page.mean_abs_diff(water, water_again)

        assert view.slider_to_min("Water density") == 0.0
        clear = view.wait_for_render(MAX_RES, previous=water_again)
        page.screenshot(path=str(tmp_path / "3-density-0.png"))
        measured["density0_vs_no_water"] = viewer_page.mean_abs_diff(clear, no_water)
        measured["density0_vs_water"] = viewer_page.mean_abs_diff(clear, water_again)

    (tmp_path / "measured.json").write_text(json.dumps(measured, indent=2))
    print("viewer pixel differences (mean abs, 0-255):", measured)
    assert measured["water_vs_no_water"] > 5.0  # the toggle changes the image
    assert measured["water_vs_water_again"] < 1.0  # and back
    assert measured["density0_vs_water"] > 5.0
    assert measured["density0_vs_no_water"] < 1.0  # no water: rgb is the clean image
