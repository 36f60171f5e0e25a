"""Ship a trained depth network as the bundled model (labrig/models/): the .onnx, its card and weights, with provenance.

Copies ``MODEL.onnx`` and its card to ``labrig/models/NAME.{onnx,json}``, and the torch weights of
its checkpoint (``MODEL.ckpt.pt``, the ``state_dict`` alone) to ``NAME.weights.pt`` for
``labrig train --init`` (``--as``: the slot in
``labrig.models.BUNDLED``, ``default`` or ``sae-only``, whose name the card takes), adding to
the card a ``bundled`` section: the sweep it was chosen from (``sweep.json`` beside it: each
width's val/test errors and latency), why it was chosen, the campaign's manifest digest and
the commands that rebuild it from nothing (campaign, ground truth, training).

    .venv/bin/python tools/bundle_model.py models/sweep/depth-w8-contact-10ms.onnx \\
        --campaign-command "labrig campaign protocols/paper.toml --out data/paper --workers 2" \\
        --reason "fastest width within 5 % of the best test contact error"
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

from labrig.cache import sha256_of
from labrig.dataset import Dataset
from labrig.models import BUNDLED, FOLDER, WEIGHTS_SUFFIX
from labrig.pipeline.model_card import ModelCard, card_path, write_card

MAX_BYTES = 10_000_000


def training_commands(card: ModelCard) -> list[str]:
    """The ``labrig train`` commands that made the network, in order: those of the networks it was fine-tuned from
    (each card's ``init.onnx``, when its card is still there), then its own."""
    commands = [str(card.raw.get("command") or card.raw.get("reproduce") or "")]
    seen = {card.path}
    init = card.raw.get("init")
    while isinstance(init, dict) and init.get("onnx"):
        parent = card_path(Path(str(init["onnx"])))
        if parent in seen or not parent.exists():
            commands.insert(0, f"(fine-tuned from {init['onnx']}, sha256 {init.get('onnx_sha256')})")
            break
        seen.add(parent)
        earlier = ModelCard.load(parent)
        commands.insert(0, str(earlier.raw.get("command") or earlier.raw.get("reproduce") or ""))
        init = earlier.raw.get("init")
    return commands


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model", type=Path, help="the trained .onnx (its .json card beside it)")
    ap.add_argument("--campaign-command", required=True, help="the command that recorded the training campaign")
    ap.add_argument("--groundtruth-command", default="", help="the ground-truth command (default: labrig groundtruth DATA)")
    ap.add_argument("--reason", required=True, help="why this model (from the sweep)")
    ap.add_argument("--as", dest="slot", default="default", choices=sorted(BUNDLED),
                    help="which bundled network it becomes (default: default)")
    args = ap.parse_args(argv)
    onnx = args.model.with_suffix(".onnx")
    if not onnx.exists() or not onnx.with_suffix(".json").exists():
        ap.error(f"{onnx}: needs NAME.onnx and NAME.json")
    if onnx.stat().st_size > MAX_BYTES:
        ap.error(f"{onnx} is {onnx.stat().st_size / 1e6:.1f} MB; the bundled model must stay under 10 MB")
    card = ModelCard.load(card_path(onnx))
    if card.training_campaign is None:
        ap.error(f"{card.path}: no 'training_data.campaign'; bundle a network trained by `labrig train`")
    data = Path(card.training_campaign)
    manifest = Dataset(data).manifest_path
    sweep_json = onnx.parent / "sweep.json"
    sweep = json.loads(sweep_json.read_text()) if sweep_json.exists() else None
    bundled = {
        "source": str(onnx),
        "reason": args.reason,
        "sweep": sweep,
        "campaign_manifest_sha256": sha256_of(manifest) if manifest.exists() else None,
        "rebuild": [args.campaign_command, args.groundtruth_command or f"labrig groundtruth {data}",
                    *training_commands(card), f"python tools/bundle_model.py {onnx} ..."],
    }
    checkpoint = onnx.with_name(onnx.stem + ".ckpt.pt")
    if not checkpoint.exists():
        ap.error(f"{onnx}: needs its checkpoint {checkpoint.name} (the weights that labrig train --init fine-tunes)")
    target = FOLDER / f"{BUNDLED[args.slot]}.onnx"
    shutil.copyfile(onnx, target)
    write_card({**card.to_json(), "name": target.stem, "bundled": bundled}, card_path(target))
    import torch

    state = torch.load(checkpoint, map_location="cpu", weights_only=False)["model"]
    torch.save(state, target.with_name(target.stem + WEIGHTS_SUFFIX))
    print(f"{target} ({target.stat().st_size / 1e6:.1f} MB) and its card", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
