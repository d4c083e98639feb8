"""The ``mmada-rl`` command line: every sub-command explains itself."""
from __future__ import annotations

import pytest

from mmada_rl.cli import build_parser, main
from mmada_rl.envs.tasks import SUPPORTED_TASKS, TASKS

SUBCOMMANDS = ("doctor", "tasks", "collect", "merge", "info", "import-h5", "fit-tokenizers", "quickstart", "eval")


def test_top_level_help_lists_every_subcommand(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--help"])
    assert exit_.value.code == 0
    text = capsys.readouterr().out
    for name in SUBCOMMANDS:
        assert name in text


@pytest.mark.parametrize("name", SUBCOMMANDS)
def test_subcommand_help(name, capsys):
    with pytest.raises(SystemExit) as exit_:
        build_parser().parse_args([name, "--help"])
    assert exit_.value.code == 0
    assert "usage: mmada-rl " + name in capsys.readouterr().out


def test_no_subcommand_prints_help_and_fails(capsys):
    assert main([]) == 2
    assert "COMMAND" in capsys.readouterr().out


def test_collect_rejects_an_unknown_policy(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["collect", "--task", "PickCube-v1", "--episodes", "1", "--out", "x", "--policy", "magic"])
    assert exit_.value.code == 2
    assert "invalid choice: 'magic'" in capsys.readouterr().err


def test_tasks_lists_the_registry_tested_tasks_first(capsys):
    assert main(["tasks"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split()[:2] == ["task", "status"]
    rows = [line.split() for line in lines[1:1 + len(TASKS)]]
    assert [row[0] for row in rows[:len(SUPPORTED_TASKS)]] == list(SUPPORTED_TASKS)
    assert {row[0] for row in rows} == set(TASKS)
    pick = next(line for line in lines if line.startswith("PickCube-v1 "))
    assert "tested" in pick and "is_grasped, is_obj_placed" in pick and TASKS["PickCube-v1"].instruction in pick


def test_tasks_all_adds_maniskills_other_ids_with_the_generic_instruction(capsys):
    assert main(["tasks", "--all"]) == 0
    rows = [line.split() for line in capsys.readouterr().out.splitlines()[1:]]
    generic = {row[0]: row for row in rows if row[1] == "generic"}
    assert "PickSingleYCB-v1" in generic and not set(generic) & set(TASKS)
    assert generic["PickSingleYCB-v1"][-3:] == ["the", "PickSingleYCB", "task"]


@pytest.mark.parametrize("argv, message", [
    (["collect", "--task", "NoSuchTask-v1", "--episodes", "1", "--out", "OUT"], "Unknown task 'NoSuchTask-v1'"),
    (["collect", "--task", "PickCube-v1", "--episodes", "1", "--out", "OUT", "--image-size", "5"], "image_size must be"),
    (["info", "OUT"], "is not an mmada_rl buffer"),
    (["import-h5", "OUT/trajectories.h5", "--out", "OUT"], "trajectories.json not found"),
])
def test_bad_input_is_a_one_line_error(argv, message, tmp_path, capsys):
    argv = [arg.replace("OUT", str(tmp_path / "out")) for arg in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"mmada-rl {argv[0]}: error: ") and message in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()


def test_quickstart_runs_each_tasks_config_shortened_unless_full():
    """The quickstart's pretraining command: the task's CPU config, shortened by default, as it is with
    ``--full``; ``--steps``, ``--episodes`` and ``--demos`` reach the recipe; a task without a config is refused."""
    from mmada_rl.quickstart import CONFIGS, FINETUNE_RESULTS, RECIPE, SHORT_STEPS, recipe_overrides

    recipes = RECIPE.parents[1]  # the report's next step names the fine-tuning config of the same name
    for config in CONFIGS.values():
        assert (recipes / "pretrain" / "config" / f"{config}.yaml").exists()
        assert (recipes / "finetune" / "config" / f"{config}.yaml").exists()
    assert set(FINETUNE_RESULTS) == {(task, full) for task in CONFIGS for full in (False, True)}

    def overrides(*argv):
        args = build_parser().parse_args(["quickstart", *argv])
        return args, recipe_overrides(args, "RUN")

    args, short = overrides()
    assert (args.task, CONFIGS[args.task]) == ("PickCube-v1", "pickcube_cpu")
    assert short == ["run_dir=RUN", "eval.episodes=0", "model.denoiser_overrides.d_model=128", f"optim.total_steps={SHORT_STEPS}"]
    assert overrides("--full")[1] == ["run_dir=RUN", "eval.episodes=0"]  # the config's 5000 steps at d_model = 256
    args, push = overrides("--task", "PushCube-v1", "--steps", "10", "--episodes", "3", "--demos", "D")
    assert CONFIGS[args.task] == "pushcube_cpu"
    assert push == ["run_dir=RUN", "eval.episodes=0", "data.dir=D", "data.collect_episodes=3", "optim.total_steps=10"]
    assert overrides("--full", "--steps", "7")[1] == ["run_dir=RUN", "eval.episodes=0", "optim.total_steps=7"]
    with pytest.raises(SystemExit) as exit_:
        build_parser().parse_args(["quickstart", "--task", "StackCube-v1"])
    assert exit_.value.code == 2


def test_quickstart_report_names_the_next_fine_tuning_and_what_it_measured(toy_pretrain_run, pick_demos, tmp_path):
    """The report the quickstart ends with, from a real (toy) pretraining run and a real one-episode evaluation:
    its evaluation table, the fine-tuning command that continues this run, and what that command measured from
    the quickstart's own policy of the same kind (default or ``--full``)."""
    from mmada_rl.evaluation import evaluate
    from mmada_rl.quickstart import FINETUNE_RESULTS, _report

    result = evaluate(toy_pretrain_run, "PickCube-v1", episodes=1, max_episode_steps=4, progress=False)
    for argv, measured in (([], "0.16 -> 0.47"), (["--full"], "0.79 -> 0.75")):
        args = build_parser().parse_args(["quickstart", *argv])
        out = tmp_path / ("full" if args.full else "default")
        out.mkdir()  # the quickstart's output folder, made before its pretraining
        text = _report(out, toy_pretrain_run, pick_demos, result, 60.0, args).read_text()
        assert text.startswith("# mmada_rl quickstart: PickCube-v1")
        assert f"2 motion-planner episodes in {pick_demos}" in text and "| episodes | 1 |" in text
        assert (f"`python recipes/finetune/finetune.py --config-name pickcube_cpu pretrained={toy_pretrain_run} "
                f"demos.dir={pick_demos} run_dir={out / 'finetune'}`") in text
        assert FINETUNE_RESULTS["PickCube-v1", args.full] in text and measured in text
        assert (out / "learning_curve.png").stat().st_size > 0
