"""Make ``docs/images/viewer.png``: nerfstudio's viewer on a trained SeaThru checkpoint, seen
from a training camera, with the Water controls in view, photographed by headless chromium.

    python tests/browser/make_screenshot.py --load-config outputs/.../config.yml \\
        [--output docs/images/viewer.png] [--camera 1] [--output-type water_split]

Runs the viewer in this process (as ``ns-viewer`` does) so it can put the browser's camera
on a training view.
"""

from __future__ import annotations

import argparse
import io
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
import viewer_page  # noqa: E402

HIDE_REMOTE_IMAGES = 'img[alt="NerfStudio Logo"] { visibility: hidden; }'


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--load-config", type=Path, required=True)
    parser.add_argument("--output", type=Path, default=Path("docs/images/viewer.png"))
    parser.add_argument("--camera", type=int, default=1, help="training camera to look through")
    parser.add_argument(
        "--output-type", default="rgb_display", help="output shown (rgb_display, clean_display, water_split, ...)"
    )
    parser.add_argument("--max-res-steps", type=int, default=2, help="Max res = 64 + 100 * steps")
    parser.add_argument("--width", type=int, default=1400, help="page width (the 3D view gets ~4:3)")
    parser.add_argument("--height", type=int, default=800)
    parser.add_argument("--max-kb", type=int, default=290, help="quantise the PNG if it is larger")
    parser.add_argument("--timeout", type=float, default=900)
    args = parser.parse_args()

    from nerfstudio.configs.base_config import ViewerConfig
    from nerfstudio.utils.eval_utils import eval_setup
    from nerfstudio.viewer.viewer import VISER_NERFSTUDIO_SCALE_RATIO, Viewer

    from seathru_nerfstudio.config import LOOPBACK

    _, pipeline, _, step = eval_setup(args.load_config, test_mode="test")
    port = viewer_page.free_port()
    viewer = Viewer(
        ViewerConfig(websocket_host=LOOPBACK, websocket_port=port, image_format="png", max_num_display_images=0),
        log_filename=args.load_config.parent / "viewer_log_filename.txt",
        datapath=pipeline.datamanager.get_datapath(),
        pipeline=pipeline,
        train_lock=None,
    )
    dataset = pipeline.datamanager.train_dataset
    viewer.init_scene(train_dataset=dataset, train_state="completed")
    viewer.update_scene(step=step)

    camera = dataset.cameras[args.camera]
    c2w = camera.camera_to_worlds.numpy()  # OpenGL convention: looks along -z, +y up
    position = c2w[:3, 3] * VISER_NERFSTUDIO_SCALE_RATIO
    fov = float(2 * np.arctan(float(camera.cy) / float(camera.fy)))  # vertical, radians

    def look_through_training_camera() -> None:
        deadline = time.time() + 60
        while time.time() < deadline:
            clients = list(viewer.viser_server.get_clients().values())
            if clients and all(c.camera._state.update_timestamp != 0.0 for c in clients):
                break
            time.sleep(0.2)
        for client in viewer.viser_server.get_clients().values():
            with client.atomic():
                client.camera.fov = fov
                client.camera.position = position
                client.camera.look_at = position - c2w[:3, 2] * VISER_NERFSTUDIO_SCALE_RATIO
                client.camera.up_direction = c2w[:3, 1]

    max_res = 64 + 100 * args.max_res_steps
    with viewer_page.browser_page(args.width, args.height) as page:
        view = viewer_page.ViewerPage(page, f"http://127.0.0.1:{port}")
        view.open()
        look_through_training_camera()
        page.add_style_tag(content=HIDE_REMOTE_IMAGES)
        view.wait_for_label("Water")
        thumb = view.slider_thumb("Max res")
        thumb.focus()
        thumb.press("Home")
        for _ in range(args.max_res_steps):
            thumb.press("ArrowRight")
        thumb.evaluate("(el) => el.blur()")  # no value tooltip in the picture
        shown = view.wait_for_render(max_res, timeout=args.timeout)
        if view.dropdown_value("Output type") != args.output_type:
            view.choose_option("Output type", args.output_type)
            view.wait_for_render(max_res, previous=shown, timeout=args.timeout)
        page.mouse.move(5, args.height - 5)  # no tooltip
        view.show_label("sRGB display")
        png = page.screenshot()

    from PIL import Image

    image = Image.open(io.BytesIO(png)).convert("RGB")
    args.output.parent.mkdir(parents=True, exist_ok=True)
    image.save(args.output, optimize=True)
    if args.output.stat().st_size > args.max_kb * 1024:  # 256 dithered colours: no banding
        image.quantize(colors=256, method=Image.Quantize.MEDIANCUT).save(args.output, optimize=True)
    print(f"wrote {args.output} ({args.output.stat().st_size // 1024} KB), {image.size}")
    viewer.viser_server.stop()


if __name__ == "__main__":
    main()
