"""The cluster recipes cannot drift from the code: every `python -m` command that
docs/deploy.md's code blocks, deploy/slurm/ and deploy/kubernetes/ quote parses with its
module's real parser (the shell variables replaced by values a run would give them), every
shard count agrees with the size of its array / Indexed Job, and the YAML loads."""

from __future__ import annotations

import contextlib
import io
import re
import shlex
from pathlib import Path

import pytest

yaml = pytest.importorskip("yaml", reason="PyYAML (the dev extra) reads the Kubernetes files")

import deploy.router  # noqa: E402
import mapex.report  # noqa: E402
import services.evaluate  # noqa: E402
import services.predictor  # noqa: E402
import services.up  # noqa: E402
from mapex.prediction.base import MEMBER_NAMES  # noqa: E402
from mapex.shards import Shard, parse_shard  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DEPLOY_PAGE = ROOT / "docs" / "deploy.md"
SBATCH = ROOT / "deploy" / "slurm" / "evaluate.sbatch"
KUBERNETES = ROOT / "deploy" / "kubernetes"

PARSERS = {
    "services.evaluate": services.evaluate.build_parser,
    "mapex.report": mapex.report.build_parser,
    "services.predictor": services.predictor.build_parser,
    "services.up": services.up.build_parser,
    "deploy.router": deploy.router.build_parser,
}
# what the shell, Slurm, Kubernetes and GNU parallel put in place of the recipes' variables
VALUES = {
    "$SLURM_ARRAY_TASK_ID": "0",
    "$SHARDS": "8",
    "$JOB_COMPLETION_INDEX": "0",
    "$jobid": "4242",
    "$(seq 0 7)": "0 1 2 3 4 5 6 7",
    "{}": "0",
}
SHELL_STOPS = {"&&", "||", ";", "|", ":::", ">", "2>&1", "&"}

Command = tuple[str, list[str]]  # (module, its arguments)


def substituted(text: str) -> str:
    for variable, value in VALUES.items():
        text = text.replace(variable, value)
    return text


def commands_in_words(words: list[str]) -> list[Command]:
    """The `python -m MODULE ARGS` commands in shell words, including those inside a quoted
    word (`sbatch --wrap "... && python -m ..."`, `sh -c "..."`)."""
    found = []
    for i, word in enumerate(words):
        if re.fullmatch(r"(\S*/)?python3?", word) and words[i + 1 : i + 2] == ["-m"]:
            argv = []
            for arg in words[i + 3 :]:
                if arg in SHELL_STOPS:
                    break
                argv.append(arg)
            found.append((words[i + 2], argv))
        elif " " in word and re.search(r"python3? -m ", word):
            found += commands_in_words(shlex.split(word))
    return found


def commands_in_shell(text: str) -> list[Command]:
    """The commands of shell text (continuation lines joined; comment lines read as code,
    since the files quote commands in their comments too)."""
    found = []
    for line in text.replace("\\\n", " ").splitlines():
        line = line.strip().lstrip("#").strip()
        if re.search(r"python3? -m ", line):
            found += commands_in_words(shlex.split(substituted(line)))
    return found


def code_blocks(markdown: str) -> str:
    return "\n".join(re.findall(r"^```(?:bash|sh)\n(.*?)^```", markdown, re.M | re.S))


def parse(command: Command):
    module, argv = command
    assert module in PARSERS, f"a recipe quotes python -m {module}: add its parser here"
    assert not any("$" in arg for arg in argv), f"a variable left in {module} {argv}"
    errors = io.StringIO()
    try:
        with contextlib.redirect_stderr(errors):
            return PARSERS[module]().parse_args(argv)
    except SystemExit:
        pytest.fail(f"python -m {module} {shlex.join(argv)}: {errors.getvalue().strip()}")


def checked(command: Command) -> tuple[str, object]:
    """Parse a command; an evaluation's --shard must parse, a merge of folders needs --out."""
    args = parse(command)
    module = command[0]
    if module == "services.evaluate":
        assert args.shard is not None, "every cluster recipe runs shards"
        parse_shard(args.shard)
    if module == "mapex.report" and len(args.results_dirs) > 1:
        assert args.out is not None
    return module, args


def shard_counts(commands: list[Command]) -> set[int]:
    return {parse_shard(parse(c).shard).count for c in commands if c[0] == "services.evaluate"}


def test_every_command_of_the_deploy_page_parses():
    commands = commands_in_shell(code_blocks(DEPLOY_PAGE.read_text()))
    modules = [checked(command)[0] for command in commands]
    assert modules.count("services.evaluate") >= 2  # the Slurm task and GNU parallel
    assert modules.count("mapex.report") >= 2  # the Slurm merge job and GNU parallel's
    assert shard_counts(commands) == {8}  # $SHARDS, and {}/8 over $(seq 0 7)
    assert set(re.findall(r"\$\(seq 0 (\d+)\)", DEPLOY_PAGE.read_text())) == {"7"}


def test_the_slurm_array_runs_every_shard_and_then_the_merge():
    text = SBATCH.read_text()
    last = int(re.search(r"^#SBATCH --array=0-(\d+)$", text, re.M)[1])
    shards = int(re.search(r"^SHARDS=(\d+)", text, re.M)[1])
    assert shards == last + 1
    commands = commands_in_shell(text)
    assert [checked(command)[0] for command in commands] == ["mapex.report", "services.evaluate"]
    assert shard_counts(commands) == {shards}
    assert '--shard "$SLURM_ARRAY_TASK_ID/$SHARDS"' in text
    assert "--dependency=afterok:$jobid" in text


def kubernetes_documents() -> dict[str, list[dict]]:
    return {path.name: list(yaml.safe_load_all(path.read_text())) for path in KUBERNETES.iterdir()}


def container_commands(document: dict) -> list[Command]:
    spec = document["spec"]["template"]["spec"]
    found = []
    for container in spec["containers"]:
        words = [*container.get("command", []), *container.get("args", [])]
        found += commands_in_words([substituted(word) for word in words])
    return found


def test_the_kubernetes_files_load_and_their_commands_parse():
    documents = kubernetes_documents()
    assert sorted(documents) == ["evaluate.yaml", "pool.yaml", "report.yaml", "results-volume.yaml"]
    kinds = {name: [d["kind"] for d in docs] for name, docs in documents.items()}
    assert kinds["pool.yaml"] == ["Deployment", "Service"] + ["Deployment"] * len(MEMBER_NAMES)
    assert kinds["results-volume.yaml"] == ["PersistentVolumeClaim"]

    service = documents["pool.yaml"][1]
    router = f"tcp/{service['metadata']['name']}:{service['spec']['ports'][0]['port']}"
    pool = [checked(c) for d in documents["pool.yaml"] if d["kind"] == "Deployment"
            for c in container_commands(d)]  # fmt: skip
    assert [module for module, _ in pool] == ["deploy.router"] + ["services.predictor"] * 4
    assert sorted(args.member for module, args in pool[1:]) == sorted(MEMBER_NAMES)
    assert all(args.connect == [router] and args.mode == "client" for _, args in pool[1:])

    (job,) = documents["evaluate.yaml"]
    assert job["kind"] == "Job" and job["spec"]["completionMode"] == "Indexed"
    (shard,) = container_commands(job)
    module, args = checked(shard)
    assert module == "services.evaluate" and args.connect == [router] and args.members == ()
    assert parse_shard(args.shard) == Shard(0, job["spec"]["completions"])
    assert "$JOB_COMPLETION_INDEX/" in str(job)

    (report,) = documents["report.yaml"]
    (merge,) = container_commands(report)
    assert checked(merge)[1].results_dirs == [Path(args.out)]
    claim = documents["results-volume.yaml"][0]["metadata"]["name"]
    for document in (job, report):
        volumes = document["spec"]["template"]["spec"]["volumes"]
        assert [v["persistentVolumeClaim"]["claimName"] for v in volumes] == [claim]
