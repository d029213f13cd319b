"""`trivla-drake recipe FILE`: runs a recipe (recipes/trivla_cpu.yaml makes the shipped model) stage by stage,
skipping stages already done and resuming a killed one; `--dry-run` prints the plan and runs nothing."""

import argparse
import sys


def add_recipe_parser(commands) -> argparse.ArgumentParser:
    """Registers `recipe` on an argparse subparsers object."""
    parser = commands.add_parser(
        "recipe", help="run a recipe: named stages (collect, train, export, soup, refit, evaluate, tables), each with "
                       "its full config; skips stages already done, resumes a killed one",
        description=__doc__)
    parser.add_argument("recipe", help="the recipe file, e.g. recipes/trivla_cpu.yaml")
    parser.add_argument("--dry-run", action="store_true", help="print each stage, done or pending, and its command")
    parser.add_argument("--only", default=None, metavar="A,B", help="run only these stages (comma-separated)")
    parser.add_argument("--from", dest="from_stage", default=None, metavar="STAGE", help="run from this stage on")
    parser.add_argument("--set", dest="overrides", metavar="KEY=VALUE", action="append", default=[],
                        help="workdir=DIR, or STAGE.FIELD=VALUE for one stage's config (repeatable)")
    parser.add_argument("--no-progress", action="store_true", help="no progress lines")
    parser.set_defaults(run=run_recipe_command)
    return parser


def run_recipe_command(args: argparse.Namespace) -> int:
    """Loads the recipe (every stage's config typed) and runs it; errors name the stage and the field."""
    from trivla_drake.config_io import ConfigError
    from trivla_drake.recipe import StageFailed, load_recipe, run_recipe
    from trivla_drake.recipe_kinds import register_all

    register_all()
    try:
        recipe = load_recipe(args.recipe, args.overrides)
        only = [name for name in args.only.split(",") if name] if args.only else None
        run_recipe(recipe, dry_run=args.dry_run, only=only, from_stage=args.from_stage,
                   progress=not args.no_progress)
    except (ConfigError, ValueError, FileNotFoundError) as error:
        print(f"trivla-drake recipe: error: {error}", file=sys.stderr)
        return 2
    except StageFailed as error:
        print(f"trivla-drake recipe: stage {error.stage!r} failed: {error}", file=sys.stderr)
        return 1
    return 0
