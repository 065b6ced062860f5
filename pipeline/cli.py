"""`invrender` command line: dataset checks, figures, and MaterialNet predictions on your own images."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def _validate(args) -> int:
    from pipeline.data import interiorverse as iv

    root = Path(args.root)
    splits = iv.read_splits(root)
    jobs = iv.split_views(root, splits)
    rejected = []
    for split, scene, view in jobs:
        rejected.extend(iv.read_view(root, scene, view, args.max_inconsistent_fraction).rejections(split))
    bad_views = len({(r["scene"], r["view"]) for r in rejected})
    for r in rejected:
        print(f"REJECT {r['file']}: {r['reason']}")
    print(
        json.dumps(
            {
                "root": str(root),
                "views": len(jobs),
                "rejected_views": bad_views,
                "scenes": {k: len(v) for k, v in splits.items()},
            }
        )
    )
    return 1 if rejected else 0


def _sheet(args) -> int:
    from pipeline.data import interiorverse as iv
    from pipeline.data.synth.figures import contact_sheet

    root = Path(args.root)
    views = [(s, v) for s in iv.read_split(root, args.split) for v in iv.list_views(root, s)][: args.views]
    print(contact_sheet(root, views, args.out))
    return 0


def output_name(path: Path) -> str:
    """The output prefix of an input: its stem without a trailing `_im` (InteriorVerse names)."""
    stem = path.stem
    return stem[:-3] if stem.endswith("_im") else stem


def predict_files(inputs: list[str | Path], out: str | Path, checkpoint: str | Path) -> list[Path]:
    """`invrender predict`: MaterialNet maps of each input in the InteriorVerse conventions,
    `<name>_{albedo,normal,depth,material}.exr` (depth in millimetres through the export's depth scale;
    material R roughness, G metallic) and `<name>_preview.png`. Every input is read and checked, and the
    export loaded, before anything is written; returns the written files."""
    import numpy as np

    from pipeline.data.formats.exr import write_exr
    from pipeline.data.formats.photo import PhotoError, read_linear
    from pipeline.models.material_net import load_material_export, predict_maps
    from pipeline.tracking.figures import prediction_sheet

    net, meta = load_material_export(checkpoint)
    images = [(Path(p), read_linear(p)) for p in inputs]
    names = [output_name(p) for p, _ in images]
    if len(set(names)) != len(names):
        raise PhotoError(f"inputs map to the same output name: {sorted(names)}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for (path, im), name in zip(images, names, strict=True):
        maps = predict_maps(net, meta, im)
        for key, arr in maps.items():
            target = out / f"{name}_{key}.exr"
            write_exr(target, np.ascontiguousarray(arr, np.float32))
            written.append(target)
        written.append(prediction_sheet(im, maps, out / f"{name}_preview.png", title=path.name))
    return written


def _predict(args) -> int:
    written = predict_files(args.inputs, args.out, args.checkpoint)
    for path in written:
        print(path)
    return 0


def _whdr(args) -> int:
    from pipeline.data import iiw
    from pipeline.data.formats.photo import srgb_to_linear
    from pipeline.metrics.whdr import whdr

    photo = iiw.read_photo(Path(args.reflectance).parent, Path(args.reflectance).stem) / 255.0
    # like the IIW script: an 8-bit PNG is sRGB and decoded to linear unless --linear says it already is
    reflectance = photo if args.linear else srgb_to_linear(photo)
    path = Path(args.judgements)
    judgements = iiw.read_judgements(path.parent, path.stem) if path.suffix == ".json" else None
    if judgements is None:
        raise iiw.IIWError(f"{path}: judgements must be a .json file")
    print(whdr(reflectance, judgements, delta=args.delta, convention="linear"))
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="invrender", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    v = sub.add_parser("validate", help="check every view of an InteriorVerse-layout root")
    v.add_argument("root")
    v.add_argument("--max-inconsistent-fraction", type=float, default=0.01)
    v.set_defaults(func=_validate)
    s = sub.add_parser("sheet", help="contact sheet PNG (image + every map) of a few views")
    s.add_argument("root")
    s.add_argument("--out", required=True)
    s.add_argument("--split", default="test", choices=("train", "val", "test"))
    s.add_argument("--views", type=int, default=4)
    s.set_defaults(func=_sheet)
    p = sub.add_parser(
        "predict",
        help="albedo, normal, depth and material maps of your own images (EXR = linear HDR; PNG/JPG = sRGB)",
    )
    p.add_argument("inputs", nargs="+", help="images: .exr (linear HDR), .png, .jpg")
    p.add_argument("--out", required=True, help="folder for <name>_{albedo,normal,depth,material}.exr + preview")
    p.add_argument(
        "--checkpoint",
        default=str(Path("outputs") / "train_material" / "model.pt"),
        help="MaterialNet export (model.pt of train_material or finetune; default: %(default)s)",
    )
    p.set_defaults(func=_predict)
    w = sub.add_parser("whdr", help="WHDR of a reflectance PNG against IIW judgements (as the IIW script)")
    w.add_argument("reflectance", help="8-bit PNG, sRGB-encoded unless --linear")
    w.add_argument("judgements", help="IIW <id>.json")
    w.add_argument("--linear", action="store_true", help="the PNG holds linear reflectance: score it as read")
    w.add_argument("--delta", type=float, default=0.1)
    w.set_defaults(func=_whdr)
    args = parser.parse_args(argv)
    from pipeline.data.formats.photo import PhotoError
    from pipeline.data.iiw import IIWError
    from pipeline.data.interiorverse import DatasetError
    from pipeline.models.export import ExportError

    try:
        return args.func(args)
    except (DatasetError, PhotoError, ExportError, IIWError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
