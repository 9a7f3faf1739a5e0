"""Style from a picture: the head stylized after five pictures, measured with a network that did not guide.

On one reconstruction of the shipped head (the main job's settings, ``guidance=imagenet``: the style features and
the content term are EfficientNet-Lite0's), each picture of ``python -m nerfart_plugin.data.style_pictures`` (four
scikit-image photographs and one drawn here) stylizes it alone (``+style_image=``), the same steps as a text run.
On the held-out views, source vs stylized (``metrics.json``'s ``style_image`` block):

* style distance with the judge's EfficientNet-Lite2 features (blocks 1-3), a network the run never saw: the
  Gram-matrix distance and the NNFM distance of the subject's pixels to the picture's (lower: closer);
* colour: the Earth mover's distance per Lab channel (summed) of the subject's pixels to the picture's;
* content: the silhouette IoU with the source (>= 0.8) and the edge similarity (1: the same edges);
* time: the fit's seconds against the README's text run (``+prompt="brain coral"``) of the same steps.

Then one run from a picture and a prompt together, and an ablation of the matched layers on one picture
(Lite0 block1 / block2 / block1+2, the default / block1-3). The picture picture | source | stylized, one row each,
goes to ``docs/images/style_image.png``.

    python -m benchmarks style_image --out-root /tmp/styles                 # trains what is missing, then measures
    python -m benchmarks style_image --out-root /tmp/styles --report-only    # the section from the raw file
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Any, Sequence

from benchmarks import common

ROOT = Path(__file__).resolve().parents[1]
log = logging.getLogger("bench.style_image")
NAME = "style_image"
#: the video and meshes are skipped: they change no trained result or measure
SETTINGS = ("guidance=imagenet", "stylize.video_frames=0", "export.enabled=false")
PROMPT = "brain coral"
#: the picture of the text + picture run and of the layer ablation
BOTH_PICTURE, ABLATION_PICTURE = "swirls", "hubble"
#: matched layers of the ablation (Lite0 blocks); "auto" is block1, block2
ABLATION = (["block1"], ["block2"], ["block1", "block2", "block3"])
IMAGES = ROOT / "docs" / "images"


def train(root: Path, extra: Sequence[str]) -> Path:
    """The stylization of ``extra`` (a picture, a prompt or both), trained or reused."""
    return common.trained_run(root, [*SETTINGS, *extra])


def row(folder: Path) -> dict[str, Any]:
    """What one run recorded: its style distances, content measures and fit time."""
    m = json.loads((folder / "metrics.json").read_text())
    out = {"folder": str(folder), "fit_s": m["stage_seconds"]["fit"], "steps": m["steps"],
           "silhouette_iou": m["silhouette_iou"], "edge_similarity": m["edge_similarity"],
           "layers": (m.get("auto") or {}).get("style_image.layers")}
    if "style_image" in m:
        out["style"] = {k: v for k, v in m["style_image"].items() if k not in ("file",)}
    if "stylized" in (m.get("judge") or {}):
        out["judge"] = {"p_source": m["judge"]["source"]["mean_target_prob"],
                        "p": m["judge"]["stylized"]["mean_target_prob"], "top5": m["judge"]["stylized"]["top5_rate"]}
    return out


def picture(pictures: dict[str, Path], folders: dict[str, Path], both: Path) -> Path:
    """One row per run: the style picture | source | stylized (the first held-out view); the text + picture run
    last."""
    import imageio.v3 as iio
    import torch

    from nerfart_plugin.guidance.style_image import read_style_image
    from nerfart_plugin.utils.images import image_grid, label_image, save_image, side_by_side, to_uint8

    rows = []
    for name, folder in [*folders.items(), (f"{BOTH_PICTURE} + \"{PROMPT}\"", both)]:
        held = sorted((folder / "heldout").glob("stylized_*.png"))[0]
        source, stylized = iio.imread(held.with_name(held.name.replace("stylized_", "source_"))), iio.imread(held)
        h = stylized.shape[0]
        pic = read_style_image(pictures[name.split(" ")[0]])
        pic = torch.nn.functional.interpolate(pic[None], size=(h, round(h * pic.shape[2] / pic.shape[1])),
                                              mode="bilinear", antialias=True)[0].permute(1, 2, 0)
        tiles = [label_image(to_uint8(pic), name), label_image(to_uint8(source), "source"),
                 label_image(to_uint8(stylized), "stylized")]
        r = tiles[0]
        for t in tiles[1:]:
            r = side_by_side(r, t, labels=None)
        rows.append(r)
    return save_image(image_grid(rows, ncols=1), IMAGES / "style_image.png")


def measure(root: Path, names: Sequence[str], ablation_runs: bool = True) -> dict[str, Any]:
    from nerfart_plugin.data.style_pictures import PICTURES, write_pictures

    pictures = write_pictures(root / "styles")
    folders = {n: train(root, [f"style_image.file={pictures[n]}"]) for n in names}
    text = train(root, [f"+prompt={json.dumps(PROMPT)}"])
    both = train(root, [f"style_image.file={pictures[BOTH_PICTURE]}", f"+prompt={json.dumps(PROMPT)}"])
    ablation = {"+".join(layers): train(root, [f"style_image.file={pictures[ABLATION_PICTURE]}",
                                               f"style_image.layers=[{','.join(layers)}]"])
                for layers in (ABLATION if ablation_runs and ABLATION_PICTURE in names else ())}
    pic = picture(pictures, folders, both)
    return {"pictures": {n: {"file": str(pictures[n]), "origin": PICTURES[n][1]} for n in names},
            "runs": {n: row(f) for n, f in folders.items()}, "text": row(text), "both": row(both),
            "ablation": {"block1+block2 (auto)": row(folders[ABLATION_PICTURE]),
                         **{k: row(f) for k, f in ablation.items()}} if ablation else {},
            "picture": str(pic)}


def _closer(r: dict[str, Any], key: str) -> str:
    s = r["style"]
    return f"{s[f'{key}_source']:.3f} -> {s[f'{key}_stylized']:.3f}"


def report(raw: dict[str, Any], info: dict[str, Any], cmd: str) -> str:
    text_s = raw["text"]["fit_s"]
    body = ["The shipped head, `guidance=imagenet` (Lite0 features for the style and the content), the main job's "
            f"steps ({raw['text']['steps']}); distances on the held-out views' subject pixels, source -> stylized, "
            "with the judge's Lite2 features (lower: closer to the picture).", ""]
    rows = []
    for name, r in raw["runs"].items():
        s = r["style"]
        margin = 1 - s["nnfm_stylized"] / s["nnfm_source"]
        rows.append([name, _closer(r, "gram"), _closer(r, "nnfm"), f"{margin:.0%}",
                     f"{s['colour_emd_source']:.1f} -> {s['colour_emd_stylized']:.1f}", f"{r['silhouette_iou']:.3f}",
                     f"{r['edge_similarity']:.3f}", f"{r['fit_s'] / text_s:.2f}x"])
    body += common.md_table(["picture", "Gram distance", "NNFM distance", "NNFM closer by", "colour EMD (Lab)",
                             "silhouette IoU (>= 0.8)", "edge similarity", "fit time vs text"], rows)
    closer = all(r["style"]["nnfm_stylized"] < r["style"]["nnfm_source"] and r["style"]["gram_stylized"]
                 < r["style"]["gram_source"] for r in raw["runs"].values())
    body += ["", f"Closer to the picture on both measures for every picture: **{'yes' if closer else 'no'}**. "
             f"The text run's fit: {text_s:.0f} s (where the root already held that run, as here, "
             "its time is from when it was trained: the ratios compare two moments of a shared machine)."]
    b = raw["both"]
    judge = b.get("judge") or {}
    body += ["", f"A picture and a prompt together (`+style_image={BOTH_PICTURE}.png +prompt=\"{PROMPT}\"`): NNFM "
             f"{_closer(b, 'nnfm')}, Gram {_closer(b, 'gram')}, the judge's P({PROMPT}) "
             f"{common.fmt(judge.get('p_source'), '.3f')} -> {common.fmt(judge.get('p'), '.3f')} (top-5 on "
             f"{common.fmt(judge.get('top5'), '.0%')} of the views), silhouette IoU {b['silhouette_iou']:.3f}."]
    if raw["ablation"]:
        body += ["", f"The matched layers, on {ABLATION_PICTURE}:", ""]
        body += common.md_table(["Lite0 layers", "Gram distance", "NNFM distance", "colour EMD", "silhouette IoU",
                                 "fit (s)"],
                                [[k, _closer(r, "gram"), _closer(r, "nnfm"),
                                  f"{r['style']['colour_emd_source']:.1f} -> {r['style']['colour_emd_stylized']:.1f}",
                                  f"{r['silhouette_iou']:.3f}", f"{r['fit_s']:.0f}"] for k, r in raw["ablation"].items()])
    body += ["", "Pictures: " + "; ".join(f"{n}: {p['origin']}" for n, p in raw["pictures"].items()) + ".", "",
             f"![picture | source | stylized]({common.rel(Path(raw['picture']), ROOT)})"]
    return common.section(NAME, "Style from a picture", cmd, info, body, False)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out-root", type=Path, default=ROOT / "outputs" / "benchmarks" / "style_image")
    p.add_argument("--pictures", nargs="+", default=["hubble", "stain", "coffee", "retina", "swirls"])
    p.add_argument("--no-ablation", action="store_true", help="skip the matched-layers ablation (three more runs)")
    common.add_raw_args(p)
    common.add_common_args(p)
    args = p.parse_args(argv)
    info = common.start_logging(log)
    raw = common.raw_results(args, NAME, lambda: measure(args.out_root, args.pictures, not args.no_ablation))
    common.finish(args, NAME, report(raw, info, common.command("style_image.py", argv or sys.argv[1:])))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
