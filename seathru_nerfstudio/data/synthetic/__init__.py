"""Synthetic forward-facing underwater / foggy scenes with exact ground truth.

``seathru-synth --output-dir DIR [--preset water|fog|none] [--seed N] ...`` ray-casts a small
analytic scene (a textured back wall with an irregular top edge, a ground plane, and a few
spheres and boxes) from an LLFF-like forward-facing rig and adds a scattering medium with the
SeaThru image formation model (as in Levy et al., CVPR 2023), per ray and per channel::

    I = J * exp(-beta_D * z) + B_inf * (1 - exp(-beta_B * z))

Conventions (all outputs):

* colours are **linear** radiance in [0, 1], stored as 16-bit RGB PNG (value / 65535);
* ``z`` is the **range**: Euclidean distance in metres from the camera centre to the first
  surface along the pixel-centre ray (not the z-depth); ``inf`` where the pixel sees nothing
  ("open water"), where ``I == B_inf`` exactly and the clean image ``J`` is 0;
* with ``--supersample N`` (default 2) the medium is applied to each of the N x N rays of a
  pixel before averaging, so the model holds per ray and only approximately per pixel at
  depth edges; ``--supersample 1`` makes every pixel follow the model exactly. A pixel whose
  centre ray misses but another of its rays hits an object gets the smallest hit range, so
  ``z == inf`` exactly when all of the pixel's rays see open water;
* world units are metres; camera-to-world poses use nerfstudio's OpenGL convention (camera
  looks along -z, +y up, +x right), world +y is up.

Layout of ``DIR``::

    transforms.json                 nerfstudio format, with train/val/test_filenames splits; each
                                    frame names its ground truth (gt_clean_file_path,
                                    gt_depth_file_path: see data/ground_truth.py)
    images/frame_00000.png          I (with medium), 16-bit linear RGB
    depth/frame_00000.png           sparse SfM-like z-depth, 16-bit millimetres, 0 = unknown
    ground_truth/clean/frame_*.png  J (no medium), 16-bit linear RGB
    ground_truth/depth/frame_*.npy  float32 HxW range in metres, inf = open water
    ground_truth/medium.json        medium parameters (1/m) and generation settings

The output is deterministic given ``--seed`` (byte-identical files), and written atomically
(built in a temporary sibling folder and renamed into place).

Modules: :mod:`.noise` (procedural noise), :mod:`.scene` (primitives, textures, shading),
:mod:`.cameras` (rig, intrinsics, rays), :mod:`.render` (medium presets, image formation,
sparse depth) and :mod:`.cli` (``seathru-synth``: options and writing the folder).
"""

from seathru_nerfstudio.data.synthetic.cli import SynthConfig, SynthError, entrypoint, generate
from seathru_nerfstudio.data.synthetic.render import PRESETS, apply_medium
from seathru_nerfstudio.data.synthetic.scene import GROUND_Y, WALL_Z

__all__ = ["GROUND_Y", "PRESETS", "WALL_Z", "SynthConfig", "SynthError", "apply_medium", "entrypoint", "generate"]
