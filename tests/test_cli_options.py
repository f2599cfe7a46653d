"""What ``--help`` says and what the options are called: the defaults a run's preset gives its
``--inference.*`` and ``--finetune.*`` options, and ``dvfb zeroshot``'s options of online inference,
named after what they configure, with their old names still working."""

from __future__ import annotations

import pytest

from dvfb.cli import build_parser, main
from dvfb.runs.presets import preset_config


def _help(argv: list[str], capsys) -> str:
    with pytest.raises(SystemExit) as info:
        main([*argv, "--help"])
    assert info.value.code == 0
    return " ".join(capsys.readouterr().out.split())  # argparse wraps at the terminal's width


def test_zeroshot_and_finetune_help_show_the_defaults_of_each_preset(capsys):
    small, paper, code = (preset_config(p, "dvfb") for p in ("small", "paper", "code"))
    assert small.inference.eval_episodes != paper.inference.eval_episodes == code.inference.eval_episodes
    text = _help(["zeroshot"], capsys)
    assert (f"--inference.eval-episodes INFERENCE.EVAL_EPISODES Mean-action evaluation episodes with the inferred z_r. "
            f"(default: the run's, by its preset: small {small.inference.eval_episodes}; paper and code "
            f"{paper.inference.eval_episodes})") in text
    assert f"(default: the run's, {small.inference.steps} at every preset)" in text
    text = _help(["finetune"], capsys)
    assert (f"(default: the run's, by its preset: small {small.finetune.frames}; paper and code "
            f"{paper.finetune.frames})") in text
    assert "(default: 100000)" not in text and "(default: 50)" not in text


def _help_groups(argv: list[str], capsys) -> dict[str, str]:
    """The help's groups: title -> the text below it (argparse's layout: a title line ending in ':')."""
    with pytest.raises(SystemExit):
        main([*argv, "--help"])
    groups: dict[str, list[str]] = {}
    title = ""
    for line in capsys.readouterr().out.splitlines():
        if line and not line.startswith(" ") and line.endswith(":"):
            title = line[:-1]
            groups[title] = []
        elif title:
            groups[title].append(line)
    return {name: " ".join(" ".join(lines).split()) for name, lines in groups.items()}


def test_finetune_help_lists_each_protocols_options_under_its_name(capsys):
    groups = _help_groups(["finetune"], capsys)
    schedule = groups["finetune options of every protocol (FinetuneSchedule)"]
    dual_value = groups["--protocol dual_value (FinetuneConfig)"]
    latent_search = groups["--protocol latent_search (LatentSearchConfig)"]
    urlb = groups["--protocol urlb (DDPGFinetuneConfig)"]
    online = groups["--protocol online_inference (OnlineInferenceConfig)"]
    assert "--finetune.frames" in schedule and "--finetune.frames" not in dual_value
    assert "the fine-tuner of fb, dvfb" in dual_value and "--finetune.eta " in dual_value
    assert "chosen with --protocol latent_search instead of dual_value" in latent_search
    assert "--finetune.method " in latent_search and "--finetune.eta " not in latent_search
    # An option two fine-tuners share is listed once, and named in the other's description.
    assert "--finetune.cov-ridge " in dual_value and "also --finetune.cov-ridge (listed under dual_value)" \
        in latent_search
    assert "--finetune.init-critic " in urlb and "the fine-tuner of rnd" in urlb
    assert "--finetune.rule " in online and "--finetune.rule " not in urlb


def test_zeroshot_names_online_inference_options_after_it_and_keeps_the_old_names(capsys):
    text = _help(["zeroshot"], capsys)
    assert "--online-inference.rule" in text and "--finetune." not in text
    common = ["zeroshot", "RUN", "--task", "walker_walk", "--protocol", "online_inference"]
    args = build_parser().parse_args([*common, "--online-inference.frames", "300", "--finetune.rule", "ts"])
    assert getattr(args, "online-inference.frames") == 300 and getattr(args, "online-inference.rule") == "ts"
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["dvfb zeroshot: note: --finetune.rule is deprecated; use --online-inference.rule"]


def test_online_inference_options_without_the_protocol_are_refused(tmp_path, capsys):
    assert main(["zeroshot", str(tmp_path / "run"), "--task", "walker_walk", "--online-inference.frames", "300"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--online-inference.* options configure --protocol online_inference" in err[0]
