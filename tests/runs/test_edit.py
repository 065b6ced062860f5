"""Stage `edit` and `invrender insert` / `invrender edit` on micro data, with untrained exports (the
numbers are not the point here: the rows, intervals, files and refusals are), and the oracle row checked
against Mitsuba: with exact incident light the render layer reproduces Mitsuba's render of the object."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.conftest import compose_cfg

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def exports(micro_exports):
    return micro_exports


def test_stage_scores_every_row_with_paired_intervals(micro_root, micro_shards, exports, tmp_path):
    from pipeline.runs.edit import ROWS, run

    cfg = compose_cfg(
        "edit",
        [
            "profile=micro",
            f"data_root={micro_root}",
            f"data_dir={micro_shards}",
            f"material_path={exports / 'material.pt'}",
            f"light_path={exports / 'light.pt'}",
            f"report_dir={tmp_path / 'report'}",
            "progress=false",
            "bootstrap=200",
            "figure_cases=2",
            f"ood.data_root={micro_root.parent / 'synthesize_ood'}",
        ],
    )
    metrics = run(cfg)
    assert all(np.isfinite(v) for v in metrics.values())
    for group in ("insert/all", "edit/all"):
        assert metrics[f"{group}/cases"] >= 1
        for row in ROWS:
            assert all(f"{group}/{row}/{s}" in metrics for s in ("psnr", "ssim", "log_l1"))
        for row in ROWS[1:]:
            verdict = metrics[f"{group}/lightnet_minus_{row}/psnr_verdict"]
            if f"{group}/lightnet_minus_{row}/psnr_lo" not in metrics:  # cases from one view: no interval
                assert verdict == 0
                continue
            lo, d, hi = (metrics[f"{group}/lightnet_minus_{row}/psnr_{k}"] for k in ("lo", "diff", "hi"))
            assert lo <= d + 1e-9 and d <= hi + 1e-9
            assert verdict == (1.0 if lo > 0 else -1.0 if hi < 0 else 0.0)
    # the ring: every object case scored around it without and with differential rendering (the rows'
    # changes rendered at scoring.ring.spp), views resampled
    assert cfg.scoring.ring.enabled and metrics["scoring_spp/ring"] == cfg.scoring.ring.spp
    assert metrics["insert/all/ring/cases"] >= 1
    for row in ("no_shadows", "lightnet", "scaled_constant", "nearest_probe"):
        assert all(f"insert/all/ring/{row}/{s}" in metrics for s in ("psnr", "psnr_surround"))
    assert "insert/all/ring/lightnet_minus_no_shadows/psnr_diff" in metrics
    report = tmp_path / "report"
    rows = (report / "cases.csv").read_text().splitlines()
    assert "ring_lightnet/psnr" in rows[0].split(",")
    n_cases = metrics["insert/all/cases"] + metrics["edit/all/cases"]
    assert len(rows) == 1 + n_cases
    for name in ("metrics.json", "timings.json", "insertion.png", "editing.png", "shadows.png"):
        assert (report / name).is_file(), name
    assert set(json.loads((report / "metrics.json").read_text())) == set(metrics)
    # every view has a sphere and the project's mesh (a vase): each shape summarised on its own
    assert metrics["insert/sphere/cases"] >= 1 and metrics["insert/vase/cases"] >= 1
    shapes = ("insert/sphere/cases", "insert/vase/cases", "insert/snowman/cases")
    assert sum(metrics.get(k, 0) for k in shapes) == metrics["insert/all/cases"]
    # the out-of-distribution rooms' insertion cases, by the rows of `ood.rows` (no oracle, no edits)
    ood_rows = tuple(cfg.ood.rows)
    assert metrics["ood/insert/all/cases"] >= 1 and "ood/edit/all/cases" not in metrics
    assert all(f"ood/insert/all/{row}/psnr" in metrics for row in ood_rows)
    assert not any(k.startswith("ood/") and "/oracle/" in k for k in metrics)
    assert all(f"ood/insert/all/lightnet_minus_{row}/psnr_diff" in metrics for row in ood_rows[1:])
    ood_cases = (report / "ood_cases.csv").read_text().splitlines()
    assert len(ood_cases) == 1 + metrics["ood/insert/all/cases"]
    assert all(line.split(",")[0].startswith("ood_") for line in ood_cases[1:])
    assert (report / "ood_insertion.png").is_file()


def test_an_ood_root_without_cases_is_refused_before_scoring(micro_root, micro_shards, exports, tmp_path):
    """`ood.data_root` is checked before the main set's long scoring: a root with no test view with cases
    is refused naming it, and nothing is written."""
    from pipeline.data.interiorverse import DatasetError
    from pipeline.runs.edit import run

    empty = tmp_path / "no_ood"
    empty.mkdir()
    cfg = _micro_edit_cfg(
        micro_root, micro_shards, exports, f"report_dir={tmp_path / 'report'}", f"ood.data_root={empty}"
    )
    with pytest.raises(DatasetError, match="no_ood"):
        run(cfg)
    assert not (tmp_path / "report").exists()
    with pytest.raises(ValueError, match="ood.rows"):
        run(_micro_edit_cfg(micro_root, micro_shards, exports, "ood.rows=[nearest_probe]"))


@pytest.mark.parametrize("shape", ["sphere", "vase"])
def test_oracle_render_matches_mitsuba_within_its_noise(micro_root, mitsuba_variant, shape):
    """An object's pixels rendered by the MC layer under the oracle (Mitsuba's radiance for each sample
    ray) against Mitsuba's own render of those pixels at 2048 spp. The per-pixel differences d_i are
    independent with mean zero when the evaluation is exact, so t = mean(d) / (sd(d)/sqrt(M)) is within
    +-4 per channel; beyond the noise, a model allowance of 10 % of the mean covers the known BRDF model
    differences (Mitsuba's separable Smith shadowing and its principled Fresnel against ours; measured
    here at 0-8 % on metals)."""
    from pipeline.data import cases as case_io
    from pipeline.data import interiorverse as iv
    from pipeline.data.synth import mitsuba_backend as mb
    from pipeline.data.synth.cases import InsertedObject, room_with_object
    from pipeline.data.synth.oracle import MitsubaOracle
    from pipeline.data.synth.scene import Room
    from pipeline.models.insertion import composite_gbuffer, gbuffers_from_maps, render_case
    from pipeline.models.render_layer import MCRenderLayer

    found = None
    for split in ("val", "test"):
        for scene in iv.read_split(micro_root, split):
            for view in iv.list_views(micro_root, scene):
                maps = iv.read_view(micro_root, scene, view).maps
                H, W = maps["im"].shape[:2]
                for c in case_io.read_cases(micro_root, scene, view, H, W):
                    if c.kind != "object" or c.description["kind"] != shape or found is not None:
                        continue
                    if shape == "vase" or c.label == "mirror":  # a mirror sphere; a vase of any class
                        found = (scene, view, maps, c)
    assert found is not None, f"the micro data holds no {shape} to check"
    scene, view, maps, case = found
    room = Room.from_json(json.loads((Path(micro_root) / scene / "scene.json").read_text()))
    camera = room.cameras[int(view)]
    obj = InsertedObject(**case.description)
    gt = gbuffers_from_maps(maps, maps["mask"][..., 0] > 0.5)
    shading = composite_gbuffer(
        gt, case.pixel, albedo=case.albedo, material=case.material, normal=case.normal, depth=case.depth
    )
    oracle = MitsubaOracle(room, camera, 6, 16, seed=1)
    with torch.no_grad():
        ours = render_case(MCRenderLayer(spp=64), shading, camera.fov_x_deg, case.pixel, oracle.for_object(obj), 0)
    w2v = mb.world_from_view(camera)
    H, W = maps["im"].shape[:2]
    d = mb.view_rays(camera.fov_x_deg, W, H)[case.pixel.numpy()] @ w2v[:3, :3].T
    ref, _ = mb.radiance(
        mb.load_scene(room_with_object(room, obj), 6), np.broadcast_to(w2v[:3, 3], d.shape).copy(), d, 2048, seed=5
    )
    diff = ours.double().numpy() - ref
    se = diff.std(0, ddof=1) / np.sqrt(len(diff))
    assert np.all(np.abs(diff.mean(0)) <= 4 * se + 0.10 * ref.mean(0)), (diff.mean(0), se, ref.mean(0))


@pytest.fixture(scope="module")
def photos(micro_root, tmp_path_factory):
    """A test view as the HDR EXR synthesize wrote and as an 8-bit sRGB PNG."""
    from PIL import Image

    from pipeline.data import interiorverse as iv
    from pipeline.data.formats.photo import linear_to_srgb

    scene = iv.read_split(micro_root, "test")[0]
    exr = iv.map_path(micro_root, scene, "000", "im")
    im = iv.read_view(micro_root, scene, "000").maps["im"]
    out = tmp_path_factory.mktemp("photos")
    png = out / "photo.png"
    scaled = im * (0.4 / float(np.median(im)))
    Image.fromarray(np.round(linear_to_srgb(np.clip(scaled, 0, 1)) * 255).astype(np.uint8)).save(png)
    return {"exr": exr, "png": png, "size": im.shape[:2]}


def _models(exports):
    return ["--material-net", str(exports / "material.pt"), "--light-net", str(exports / "light.pt"), "--spp", "4"]


@pytest.mark.parametrize("kind", ["png", "exr"])
def test_insert_and_edit_composite_into_the_photo(photos, exports, tmp_path, kind):
    from PIL import Image

    from pipeline.cli import main
    from pipeline.data.formats.exr import read_exr
    from pipeline.data.formats.photo import read_linear

    H, W = photos["size"]
    photo = read_linear(photos[kind])
    out = tmp_path / "ins.png"
    args = ["insert", str(photos[kind]), "--at", f"{H // 2},{W // 2}", "--object", "snowman", "--material", "glossy"]
    assert main([*args, "--no-shadows", "--out", str(out), *_models(exports)]) == 0
    result = read_exr(tmp_path / "ins.exr")
    changed = np.abs(result - photo).max(-1) > 0
    assert 0 < changed.sum() < H * W / 2  # the object's pixels, and only those
    assert np.isfinite(result).all()
    # with its shadows (the default): the same object pixels, and the room around it changed too
    assert main([*args, "--out", str(tmp_path / "shadowed.exr"), *_models(exports)]) == 0
    shadowed = read_exr(tmp_path / "shadowed.exr")
    assert np.array_equal(shadowed[changed], result[changed])
    around = (np.abs(shadowed - photo).max(-1) > 0) & ~changed
    assert 0 < around.sum() < H * W / 2 and np.isfinite(shadowed).all() and (shadowed >= 0).all()
    rows, cols = np.nonzero(around)  # near the object: within the bounding box of its pixels, widened
    obj_rows, obj_cols = np.nonzero(changed)
    span = max(np.ptp(obj_rows), np.ptp(obj_cols)) * 3 + 2
    assert rows.min() >= obj_rows.min() - span and rows.max() <= obj_rows.max() + span
    assert cols.min() >= obj_cols.min() - span and cols.max() <= obj_cols.max() + span
    png = np.asarray(Image.open(out))
    assert png.shape == (H, W, 3)
    if kind == "png":  # untouched pixels round-trip to the input's own 8-bit values
        original = np.asarray(Image.open(photos["png"]).convert("RGB"))
        assert np.array_equal(png[~changed], original[~changed])
    mask = np.zeros((H, W), np.uint8)
    mask[H // 4 : H // 2, W // 4 : W // 2] = 255
    Image.fromarray(mask).save(tmp_path / "mask.png")
    edit = ["edit", str(photos[kind]), "--mask", str(tmp_path / "mask.png"), "--metallic", "1", "--roughness", "0.1"]
    assert main([*edit, "--out", str(tmp_path / "ed.exr"), *_models(exports)]) == 0
    edited = read_exr(tmp_path / "ed.exr")
    outside = mask == 0
    assert np.array_equal(edited[outside], photo[outside]) and not np.array_equal(edited[~outside], photo[~outside])
    assert (tmp_path / "ed.png").is_file()


def test_objects_stand_on_the_geometry_given(micro_root, exports):
    """`insert_into(stand_on=...)`: the predicted G-buffers given explicitly change nothing (same seed, same
    image); the ground truth's put the object, its visibility and its shadow's proxy elsewhere."""
    from pipeline.data import interiorverse as iv
    from pipeline.models.insertion import InsertedObject, insert_into, prepare_view
    from pipeline.models.light_net import load_light_export
    from pipeline.models.material_net import load_material_export

    scene = iv.read_split(micro_root, "test")[0]
    maps = iv.read_view(micro_root, scene, "000").maps
    fov = float(iv.read_cameras(micro_root, scene)["000"]["fov_x_deg"])
    net, _ = load_light_export(exports / "light.pt")
    view = prepare_view(maps["im"], *load_material_export(exports / "material.pt"), net, fov, gt_maps=maps)
    H, W = maps["im"].shape[:2]
    obj = [InsertedObject("sphere", H // 2, W // 2)]
    plain, pixels = insert_into(view, obj, 4, 0)
    same, same_pixels = insert_into(view, obj, 4, 0, stand_on=view.pred)
    assert torch.equal(plain, same) and torch.equal(pixels, same_pixels)
    on_truth, truth_pixels = insert_into(view, obj, 4, 0, stand_on=view.gt)
    assert not torch.equal(on_truth, plain) and torch.isfinite(on_truth).all()


def test_insert_several_objects_a_mesh_and_a_material_file(photos, exports, tmp_path):
    import trimesh

    from pipeline.cli import main
    from pipeline.data.formats.exr import read_exr
    from pipeline.data.formats.photo import read_linear

    H, W = photos["size"]
    photo = read_linear(photos["exr"])
    mesh = tmp_path / "box.glb"
    trimesh.creation.box(extents=(1.0, 2.0, 1.0)).export(mesh)
    (tmp_path / "red.yaml").write_text("albedo: [0.8, 0.1, 0.1]\nroughness: 0.4\nmetallic: 0\n")
    args = ["insert", str(photos["exr"]), "--at", f"{H // 2},{W // 4}", "--object", "sphere", "--material", "mirror"]
    args += ["--at", f"{H // 2},{3 * W // 4}", "--object", str(mesh), "--material", str(tmp_path / "red.yaml")]
    assert main([*args, "--turn", "30", "--no-shadows", "--out", str(tmp_path / "two.exr"), *_models(exports)]) == 0
    result = read_exr(tmp_path / "two.exr")
    changed = np.abs(result - photo).max(-1) > 0
    cols = np.nonzero(changed)[1]
    assert (cols < W // 2).any() and (cols >= W // 2).any()  # both objects, each on its side
    assert changed.sum() < H * W / 2 and np.isfinite(result).all()
    red = result[:, W // 2 :][changed[:, W // 2 :]]
    assert red[:, 0].mean() > red[:, 2].mean()  # the material file's colour on the mesh


def test_insert_and_edit_refuse_bad_input_naming_it_and_write_nothing(photos, exports, tmp_path, capsys):
    from PIL import Image

    from pipeline.cli import main

    H, W = photos["size"]
    Image.fromarray(np.zeros((H + 1, W), np.uint8)).save(tmp_path / "big_mask.png")
    Image.fromarray(np.zeros((H, W), np.uint8)).save(tmp_path / "empty_mask.png")
    (tmp_path / "corrupt.png").write_bytes(b"\x89PNG\r\n\x1a\nnot a png")
    fan = tmp_path / "fan.obj"  # three triangles on one edge
    fan.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 -1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 2 5\n")
    bad_yaml = tmp_path / "bad.yaml"
    bad_yaml.write_text("albedo: [0.5, 0.5, 0.5]\nmetallic: 0\n")
    photo, out = str(photos["png"]), tmp_path / "outs" / "x.png"
    out.parent.mkdir()
    models = _models(exports)
    cases = {
        "--at": ["insert", photo, "--at", f"{H + 5},3", "--out", str(out), *models],
        "--at ": ["insert", photo, "--at", "3", "--out", str(out), *models],
        "--mask": [
            "edit",
            photo,
            "--mask",
            str(tmp_path / "big_mask.png"),
            "--metallic",
            "1",
            "--out",
            str(out),
            *models,
        ],
        "selects no pixel": [
            "edit",
            photo,
            "--mask",
            str(tmp_path / "empty_mask.png"),
            "--albedo",
            "1,0,0",
            "--out",
            str(out),
            *models,
        ],
        "--albedo": [
            "edit",
            photo,
            "--mask",
            str(tmp_path / "big_mask.png"),
            "--albedo",
            "2,0",
            "--out",
            str(out),
            *models,
        ],
        "at least one of": ["edit", photo, "--mask", str(tmp_path / "empty_mask.png"), "--out", str(out), *models],
        "corrupt.png": ["insert", str(tmp_path / "corrupt.png"), "--at", "3,3", "--out", str(out), *models],
        "missing.pt": [
            "insert",
            photo,
            "--at",
            "3,3",
            "--out",
            str(out),
            "--material-net",
            str(tmp_path / "missing.pt"),
        ],
        "light.pt": ["insert", photo, "--at", "3,3", "--out", str(out), "--material-net", str(exports / "light.pt")],
        "--out": ["insert", photo, "--at", "3,3", "--out", str(tmp_path / "nowhere" / "x.png"), *models],
        "--scale 0": ["insert", photo, "--at", "3,3", "--scale", "0", "--out", str(out), *models],
        "room's depth": ["insert", photo, "--at", f"{H // 2},{W // 2}", "--scale", "1000", "--out", str(out), *models],
        "non-manifold": ["insert", photo, "--at", "3,3", "--object", str(fan), "--out", str(out), *models],
        "given 2 times for 3 --at": [
            "insert",
            photo,
            *("--at", "3,3", "--at", "4,4", "--at", "5,5"),
            *("--turn", "10", "--turn", "20"),
            *("--out", str(out), *models),
        ],
        "missing key 'roughness'": ["insert", photo, "--at", "3,3", "--material", str(bad_yaml), "--out", str(out)],
        ".jpg": ["insert", photo, "--at", "3,3", "--out", str(tmp_path / "x.jpg"), *models],
    }
    for needle, argv in cases.items():
        assert main(argv) == 2, needle
        err = capsys.readouterr().err
        assert needle.strip() in err and "Traceback" not in err, (needle, err)
        assert not any(out.parent.iterdir()), needle


def test_cli_material_choices_are_the_scored_classes():
    from pipeline.cli import MATERIAL_CLASSES
    from pipeline.data.synth.cases import OBJECT_CLASSES
    from pipeline.models.insertion import OBJECT_MATERIALS

    assert set(MATERIAL_CLASSES) == set(OBJECT_MATERIALS) == set(OBJECT_CLASSES)
    for name, (rough, metal) in OBJECT_CLASSES.items():  # the CLI inserts what the stage scores
        assert OBJECT_MATERIALS[name][1:] == (rough, metal)


def test_prepared_view_holds_the_photo_both_gbuffers_and_their_contexts(micro_root, exports):
    """What the stage, `invrender insert/edit` and the insertion bench render from (`prepare_view`): the
    photo as read, G-buffers with depth zeroed outside the mask, a context per G-buffer set."""
    from pipeline.data import cases as case_io
    from pipeline.models.insertion import prepare_view
    from pipeline.models.light_net import load_light_export
    from pipeline.models.material_net import load_material_export

    scene, view = case_io.case_views(micro_root, "test")[0]
    maps, cases, camera = case_io.read_case_view(micro_root, scene, view, "test")
    material = load_material_export(exports / "material.pt")
    net, _ = load_light_export(exports / "light.pt")
    mask = maps["mask"][..., 0] > 0.5
    fov = float(camera["fov_x_deg"])
    v = prepare_view(maps["im"], *material, net, fov, mask=mask, gt_maps=maps)
    H, W = maps["im"].shape[:2]
    assert cases and v.fov == fov and v.image.shape == (1, 3, H, W)
    assert torch.equal(v.photo, torch.from_numpy(maps["im"]).float())
    for gb in (v.pred, v.gt):
        assert gb["depth"].shape == (1, H, W) and (gb["depth"][0][~torch.from_numpy(mask)] == 0).all()
    assert v.ctx_pred is not None and v.ctx_gt is not None
    assert float(v.scale) == pytest.approx(float(np.clip(maps["im"], 0, None).mean()), rel=1e-4)
    bare = prepare_view(maps["im"], *material, net, fov)  # a photo of one's own: no mask, no ground truth
    assert bare.gt is None and bare.ctx_gt is None
    assert torch.equal(bare.pred["albedo"], v.pred["albedo"])
    # ssrt_depth=every_pixel: the predicted depth where the mask is off too, the ground truth still masked
    every = prepare_view(maps["im"], *material, net, fov, mask=mask, gt_maps=maps, mask_prediction=False)
    assert torch.equal(every.pred["depth"], bare.pred["depth"]) and (every.pred["depth"] > 0).all()
    assert torch.equal(every.gt["depth"], v.gt["depth"])


def test_rows_on_the_same_shading_draw_the_same_directions(micro_root, micro_shards, exports):
    """Pairing, checked where it is exact: under a constant light an estimate is (mean of f cos / pdf over
    the drawn directions) x L, so the scaled constant's render of an object is the constant's times
    ratio * scale / constant, per channel, only if both drew the same directions. Views get seeds of
    their own."""
    from pipeline.data import interiorverse as iv
    from pipeline.systems.insertion_scoring import score_view, stage_setup, view_context

    cfg = compose_cfg(
        "edit",
        ["profile=micro", f"data_root={micro_root}", f"data_dir={micro_shards}"]
        + [f"material_path={exports / 'material.pt'}", f"light_path={exports / 'light.pt'}", "scoring.spp=4"],
    )
    with pytest.raises(ValueError, match="ssrt_depth='all'"):
        stage_setup(compose_cfg("edit", ["ssrt_depth=all"]))
    shared = stage_setup(cfg)
    seeds = set()
    for scene, view in shared["views"]:
        ctx, cases = view_context(shared, scene, view, cfg)
        seeds.add(ctx["seed"])
        objects = [c for c in cases if c.kind == "object"][:1]
        if not objects:
            continue
        res = score_view(ctx, objects, cfg)[0]
        c = shared["constants"]
        want = res["renders"]["constant"] * (c.ratio * ctx["view"].scale / c.constant)
        assert torch.allclose(res["renders"]["scaled_constant"], want, rtol=1e-5, atol=1e-7)
    test_views = [(s, v) for s in iv.read_split(micro_root, "test") for v in iv.list_views(micro_root, s)]
    assert len(seeds) == len(shared["views"]) == len(test_views)


def _micro_edit_cfg(micro_root, micro_shards, exports, *more):
    return compose_cfg(
        "edit",
        ["profile=micro", f"data_root={micro_root}", f"data_dir={micro_shards}", "progress=false", *more]
        + [f"material_path={exports / 'material.pt'}", f"light_path={exports / 'light.pt'}"],
    )


def test_the_stages_scoring_is_converged_on_micro_cases(micro_root, micro_shards, exports):
    """Every row but the oracle of the first micro test view's cases, at the `edit` stage's own samples per
    pixel (tiny's `scoring`) and at 4x them: no class's mean PSNR moves by more than 0.1 dB
    (`bench.scoring_convergence`), the nearest probe's sharp light included; nor, on the first test view
    with an object on a surface, does the PSNR on the ring around it (`scoring.ring.spp`) under LightNet's
    or the scaled constant's light, or without shadows. The
    oracle's light is noisy itself: the next test checks its decorrelated PSNR."""
    from pipeline.bench import scoring_convergence as sc
    from pipeline.systems.insertion_scoring import ROWS

    tiny = compose_cfg("edit", [])
    counts = [f"scoring.spp={tiny.scoring.spp}"]
    counts += [f"scoring.row_spp.{row}={n}" for row, n in tiny.scoring.row_spp.items()]
    cfg = _micro_edit_cfg(micro_root, micro_shards, exports, *counts)
    rows = tuple(row for row in ROWS if row != "oracle")
    records = sc.measure(cfg, [1, 4], rows, max_views=1, progress=False)
    assert records, "the first micro test view holds no case"
    summary = sc.summarise(records, [1, 4], rows, 0.1, resamples=200)
    moved = {row: summary["classes"]["all"]["rows"][row]["change_at_4x"]["1"]["diff"] for row in rows}
    assert summary["converged_scale"] == dict.fromkeys(rows, 1), moved

    from pipeline.data import cases as case_io

    def has_ring(scene, view):  # an object on a surface: room around it that it changes
        _, cases, _ = case_io.read_case_view(micro_root, scene, view, "test")
        return any(c.kind == "object" and len(c.ring_pixel) for c in cases)

    view = next(f"{s}/{v}" for s, v in case_io.case_views(micro_root, "test") if has_ring(s, v))
    on_ring = ("lightnet", "scaled_constant", "nearest_probe")
    records = sc.measure(cfg, [1, 4], on_ring, progress=False, view_ids=[view], ring=True)
    ring = sc.summarise_ring(records, [1, 4], resamples=200)  # the ring at tiny's scoring.ring.spp and 4x
    assert ring and set(ring) <= {"ring_no_shadows", "ring_lightnet", "ring_scaled_constant", "ring_nearest_probe"}
    # the smooth lights only: the nearest probe's sharp one moved -0.12 dB at 4x on this view in one
    # session (+/-0.1 in another), so its ring at scoring.ring.spp is not claimed converged (results.md)
    ring_moved = {name: entry["change_at_4x"]["1"]["diff"] for name, entry in ring.items()}
    smooth = ("ring_no_shadows", "ring_lightnet", "ring_scaled_constant")
    assert all(abs(ring_moved[name]) <= 0.1 for name in smooth if name in ring_moved), ring_moved


def test_the_oracles_converged_error_does_not_depend_on_its_samples(micro_root, micro_shards, exports):
    """The oracle's light is Mitsuba's noisy paths, so its plain squared error falls with its samples; the
    extrapolated one (`oracle.psnr: extrapolated`) estimates the converged render's and must not. On the
    first micro object case at 32 sample rays (noise variance a few times the squared error), over 16
    seeds: the mean extrapolated MSE at 4x the samples equals that at 1x within 4 standard errors of the
    difference, while the plain MSE at 1x lies above its 4x by more than 3 (measured: 1.0 and 6.0; the
    halves' decorrelated MSE, `psnr_decorrelated`, 0.1). At 16 rays (noise 5x the error) the extrapolated
    moved 1.0 standard errors, the decorrelated 1.5."""
    from pipeline.systems import insertion_scoring as isc

    cfg = _micro_edit_cfg(micro_root, micro_shards, exports, "scoring.row_spp.oracle=32")
    assert cfg.oracle.psnr == "extrapolated"
    shared = isc.stage_setup(cfg)
    layers = {n: isc.scoring_layers(cfg, n) for n in (1, 4)}
    scene, view = shared["views"][0]
    ctx, cases = isc.view_context(shared, scene, view, cfg)
    case = next(c for c in cases if c.kind == "object")
    kinds = ("psnr", "psnr_decorrelated", "psnr_with_noise")
    mse = {(n, kind): [] for n in layers for kind in kinds}
    for seed in range(16):
        for n, layer in layers.items():
            (res,) = isc.score_view({**ctx, "seed": 1000 * seed, "layers": layer}, [case], cfg, ("lightnet", "oracle"))
            for kind in kinds:
                mse[n, kind].append(10 ** (-res["rows"]["oracle"][kind] / 10))

    def gap(kind):  # mean MSE at 1x minus at 4x, and its standard error (the seeds are independent)
        a, b = np.asarray(mse[1, kind]), np.asarray(mse[4, kind])
        return (a - b).mean(), (a - b).std(ddof=1) / np.sqrt(len(a))

    for kind in ("psnr", "psnr_decorrelated"):
        diff, se = gap(kind)
        assert abs(diff) < 4 * se, (kind, diff, se)
    diff, se = gap("psnr_with_noise")
    assert diff > 3 * se, (diff, se)  # one-sided: the noise the plain error carries is there to remove
