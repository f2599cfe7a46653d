"""``dvfb export`` and ``dvfb push``: a pre-trained model as the field shares one (docs/sharing.md)."""

from __future__ import annotations

import argparse
from pathlib import Path

from dvfb.cli.common import Formatter, integer
from dvfb.core.errors import ConfigError, RemoteError
from dvfb.runs.export import describe_export, export_model, is_export
from dvfb.workflows.resources import open_run


def cmd_export(args: argparse.Namespace) -> int:
    out = export_model(open_run(args.run), args.out, snapshot=args.snapshot,
                       with_inference_data=args.with_inference_data, inference_size=args.inference_size,
                       overwrite=args.overwrite)
    print(describe_export(out))
    return 0


def cmd_push(args: argparse.Namespace) -> int:
    path = Path(args.model)
    if not is_export(path):
        raise ConfigError(f"{path} is not an exported model (no model.safetensors and config.json of dvfb); "
                          "make one with `dvfb export RUN --out DIR`")
    try:
        # the optional hub extra, absent from a plain install (~0.19 s to import when present)
        from huggingface_hub import HfApi, get_token
        from huggingface_hub.utils import validate_repo_id
    except ImportError as exc:
        raise ConfigError("dvfb push needs the optional hub extra: pip install 'dvfb[hub]' "
                          "(huggingface_hub)") from exc
    # Everything that needs no network is checked before the first request is sent.
    if get_token() is None:
        raise ConfigError("dvfb push needs Hugging Face credentials: set HF_TOKEN or log in with `hf auth login` "
                          "(it writes the token file); nothing was sent")
    try:
        validate_repo_id(args.repo)
    except ValueError as exc:
        raise ConfigError(f"--repo {args.repo!r} is not a hub repository name (ORG/NAME): {_first_line(exc)}") \
            from exc
    api = HfApi()
    try:
        api.create_repo(args.repo, private=args.private, exist_ok=True)
        commit = api.upload_folder(folder_path=str(path), repo_id=args.repo, commit_message=args.message)
    except Exception as exc:
        # The hub client's errors are its own classes and those of whichever HTTP library its version
        # uses (requests, httpx, ...): at this point every one of them is the network's or the hub's.
        raise RemoteError(f"cannot push {path} to {args.repo}: {type(exc).__name__}: {_first_line(exc)}") from exc
    print(f"pushed {path} to {args.repo}: {commit}")
    return 0


def _first_line(exc: Exception) -> str:
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    return lines[0] if lines else "no reason given"


def register(sub, agent: str) -> None:
    p = sub.add_parser("export", help="write a run's model as safetensors + config.json + model card",
                       formatter_class=Formatter,
                       description="Write a pre-training run's model as the field shares one (docs/sharing.md): "
                                   "model.safetensors (inference weights only), config.json and a model card "
                                   "README.md, loadable with dvfb.load(DIR) without the run directory.")
    p.add_argument("run", help="pre-training run directory")
    p.add_argument("--out", required=True, help="directory to write (absent or empty)")
    p.add_argument("--snapshot", type=integer(0), default=None, help="snapshot frames (default: the newest)")
    p.add_argument("--with-inference-data", action="store_true",
                   help="add reward-inference samples from the pre-training replay (inference_data.npz)")
    p.add_argument("--inference-size", type=integer(1), default=100_000,
                   help="at most this many transitions in the inference data, chosen uniformly with the run's seed")
    p.add_argument("--overwrite", action="store_true", help="replace an exported model in --out")
    p.set_defaults(func=cmd_export)

    p = sub.add_parser("push", help="upload an exported model to the Hugging Face hub (extra: hub)",
                       formatter_class=Formatter,
                       description="Upload an exported model directory (dvfb export) to a hub repository. Needs "
                                   "the optional hub extra: pip install 'dvfb[hub]'.")
    p.add_argument("model", help="exported model directory")
    p.add_argument("--repo", required=True, help="hub repository, ORG/NAME")
    p.add_argument("--private", action="store_true", help="create the repository as private")
    p.add_argument("--message", default="Upload a dvfb model", help="commit message")
    p.set_defaults(func=cmd_push)
