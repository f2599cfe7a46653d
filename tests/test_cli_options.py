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
