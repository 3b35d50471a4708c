"""demo-factory publish: push every split of a converted dataset to the Hugging Face Hub with its card.

Pushes each split folder of a converted dataset (demo-factory convert) to the Hugging Face Hub dataset repo
REPO_ID_<split> in LeRobot's standard layout, tagged v3.0 so that LeRobotDataset('REPO_ID_<split>') and
lerobot-train --dataset.repo_id=REPO_ID_<split> load it, with the dataset card (cross-linking the other
splits) and its contact sheet. Credentials: `huggingface-cli login` or HF_TOKEN. Re-running the same command
resumes: only files that are missing or different on the Hub are uploaded.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from demo_factory.publish.plan import describe_plan, human_size, plan_publish

HUB_URL = "https://huggingface.co/datasets/"


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Register the ``publish`` sub-command on an argparse ``subparsers`` object."""
    parser = subparsers.add_parser(
        "publish", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
        help="publish a converted dataset to the Hugging Face Hub (one dataset repo per split, with its card)")
    parser.add_argument("--dataset", type=Path, required=True,
                        help="the output folder of demo-factory convert (one folder per split, README.md)")
    parser.add_argument("--repo-id", required=True, help="owner/name on the Hub; split s goes to owner/name_s")
    parser.add_argument("--private", action="store_true", help="create the repos private (and make existing ones private)")
    parser.add_argument("--dry-run", action="store_true",
                        help="list each repo, each file, the total size and the card; touch no network")
    parser.set_defaults(run=run)
    return parser


def run(args: argparse.Namespace) -> int:
    """Run the sub-command: exit 0, 2 for bad input, 1 for credential or Hub problems (one line on stderr)."""
    # A PublishError is a UsageError with its own exit code (cli_common.run_command prints it).
    plan = plan_publish(args.dataset, args.repo_id, private=args.private)
    if args.dry_run:
        print(describe_plan(plan))
        return 0
    from demo_factory.publish.hub import publish  # huggingface_hub + lerobot: only when publishing

    report = publish(plan)
    print(f"\npublished {args.dataset} as {report.user}:")
    for repo in report.repos:
        sent = (f"{len(repo.uploaded)} dataset files ({human_size(repo.uploaded_bytes)})" if repo.uploaded
                else "dataset files already up to date")
        card = ", ".join(repo.card) if repo.card else "card up to date"
        tag = "tagged v3.0" if repo.tagged else "v3.0 tag up to date"
        print(f"  {HUB_URL}{repo.repo_id}  {sent}; {card}; {tag}")
    first = report.repos[0].repo_id
    print(f"\nLoad a split from the Hub:\n  python -c 'from lerobot.datasets.lerobot_dataset import LeRobotDataset as D; "
          f"print(D(\"{first}\"))'\nTrain on it: lerobot-train --dataset.repo_id={first} ... (see the card)")
    return 0
