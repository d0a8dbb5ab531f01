"""`fieldguard train-classes`: the RGB-D pipeline's class model from annotated frames."""
from __future__ import annotations

from pathlib import Path


def cmd_train_classes(a) -> int:
    from appliance import rgbd_model
    if not 1 <= a.components <= 16:
        raise rgbd_model.RgbdModelError(f"--components must be 1..16, got {a.components}")
    if a.ridge < 0:
        raise rgbd_model.RgbdModelError(f"--ridge must be >= 0, got {a.ridge}")
    model = rgbd_model.train_from_files(a.frames, a.annotations, components=a.components,
                                        ridge=a.ridge)
    out = rgbd_model.save(model, a.out)
    rgbd_model.load(out)                    # what the daemon will read must read back
    px = model.meta.get("pixels", {})
    print(f"wrote {out}: version {rgbd_model.VERSION}, classes "
          + ", ".join(f"{c} ({px.get(c, 0)} px)" for c in model.classes)
          + f"; {len(model.meta.get('frames', []))} frames, {a.components} component(s)")
    for k in model.meta.get("unmatched_frames", []):
        print(f"note: annotated frame {k!r} was not among FRAMES")
    return 0


def register(sub) -> None:
    t = sub.add_parser("train-classes", help="train the RGB-D colour/texture class model",
                       description="Fit the rgbd pipeline's class model (Mahalanobis colour "
                                   "classes in every colour space, LBP histograms) from "
                                   "annotated rectangles/polygons; see docs/rgbd.md.")
    t.add_argument("frames", nargs="+", metavar="FRAMES", help="colour images (PNG/JPEG)")
    t.add_argument("--annotations", required=True, type=Path, help="annotation JSON file")
    t.add_argument("--out", required=True, type=Path, help="model file to write (.npz)")
    t.add_argument("--components", type=int, default=1,
                   help="Gaussians per class (1 = the paper; >1 = mixture of Gaussians)")
    t.add_argument("--ridge", type=float, default=1.0,
                   help="added to each covariance diagonal (8-bit levels^2)")
    t.set_defaults(func=cmd_train_classes)
