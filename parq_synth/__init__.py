"""parq_synth: synthetic ScanNet-layout scenes with exact ground truth, for training and
validating small PARQ models (numpy only; never imports torch).

    parq_synth.generate(out, scenes, seed, frames=60, size=(320, 240))   # out/scene_<k>/
    parq_synth.generate_scene(out_dir, seed, frames=60, size=(320, 240), index=k) -> Scene
    parq_synth.build_scene(seed, index, frames, size) -> Scene      # nothing written
    scene.render(i) -> render.View (rgb, depth, instance, hit, normal, points)

A scene is a rectangular room (3.5-7 m x 3.5-7 m x 2.5-3 m, floor at z = 0, walls at x = 0,
Lx and y = 0, Ly) with procedural floor / wall textures, 4-10 pieces of furniture of the 9
ScanNet classes built from boxes and elliptic cylinders, an ambient light plus a ceiling lamp
and sometimes sunlight (Lambertian, hard shadows), seen by a hand-held camera walking a smooth
loop at eye height (1.3-1.7 m), looking inwards and turned towards the furniture near it,
10-30 degrees down, 6-12 cm per frame.

Rendering is exact ray casting of every pixel centre with the runtime's pinhole model (see
render.py).  Measured on one core of this machine (Intel Xeon, numpy 2.4, CPU time per frame
over 80 frames of 4 scenes, shadows included; BLAS is not used, so it stays one thread):

    160 x 120:  22 ms median, 28 ms p90, 43 ms max  (26 ms/frame for a whole 60-frame
                scene with layout and PNG / pose writing)
    320 x 240:  90 ms median, 120 ms p90, 170 ms max  (95 ms/frame for a whole scene)

The cost grows with the pixels covered by furniture (bookshelves hold up to ~50 primitives).
"""
from parq_runtime import __version__

from .scene import GENERATOR_VERSION, Scene, SceneObject, build_scene
from .shapes import CLASSES, MEAN_SIZES
from .writer import generate, generate_scene

__all__ = ["CLASSES", "GENERATOR_VERSION", "MEAN_SIZES", "Scene", "SceneObject", "__version__",
           "build_scene", "generate", "generate_scene"]
