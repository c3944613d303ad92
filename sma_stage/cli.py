"""gpi_tool: fit, diagnose, simulate and reproduce the paper from the command line.

Every bad input ends with exit status 2 and one line on standard error; with --json the JSON
document is the only thing on standard output.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import NoReturn

from sma_stage.errors import InputError
from sma_stage.io.plain import strict_json
from sma_stage.model.parameters import DEFAULT_OPERATORS, check_operators

EXIT_BAD_INPUT = 2


def operator_count(text: str) -> int:
    """argparse type for --operators."""
    try:
        return check_operators(int(text))
    except (ValueError, InputError) as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def fraction(text: str) -> float:
    """A number strictly between 0 and 1 (argparse type)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number between 0 and 1, got {text!r}") from None
    if not 0.0 < value < 1.0:
        raise argparse.ArgumentTypeError(f"expected a number between 0 and 1, got {text!r}")
    return value


def worker_count(text: str) -> int:
    """A whole number from 1 to 64 (argparse type)."""
    if not text.strip().isdigit() or not 1 <= int(text) <= 64:
        raise argparse.ArgumentTypeError(f"expected a whole number from 1 to 64, got {text!r}")
    return int(text)


def sample_budget(text: str) -> int:
    """0, or a whole number of at least 1,000 (argparse type)."""
    if not text.strip().isdigit() or 0 < int(text) < 1000:
        raise argparse.ArgumentTypeError(f"expected 0 or a whole number of at least 1000, got {text!r}")
    return int(text)


def round_count(text: str) -> int:
    """An integer from 1 to 4 (argparse type)."""
    if not text.strip().isdigit() or not 1 <= int(text) <= 4:
        raise argparse.ArgumentTypeError(f"expected a whole number from 1 to 4, got {text!r}")
    return int(text)


def family_list(text: str) -> tuple[str, ...]:
    """Comma-separated model families (argparse type)."""
    from sma_stage.identify.families import check_families

    try:
        return check_families(text.split(","))
    except InputError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


class OneLineErrors(argparse.ArgumentParser):
    """An argument parser whose errors are one line on standard error (no usage block), exit status 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with one subparser per command."""
    parser = OneLineErrors(prog="gpi_tool", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    paper = commands.add_parser("paper", help="evaluate the paper's Table 1 and write what it finds")
    paper.add_argument("--operators", type=operator_count, default=DEFAULT_OPERATORS)
    paper.add_argument("--out", type=Path, default=Path("out/paper"), help="folder for plots and summary")
    paper.add_argument("--json", action="store_true", help="print the findings as JSON")
    paper.set_defaults(handler=run_paper)
    fit = commands.add_parser("fit", help="fit the GPI model to measured data")
    add_data_arguments(fit, validate_required=False)
    fit.set_defaults(handler=run_identify_command("run_fit"))
    diagnose = commands.add_parser("diagnose", help="fit, find what the model lacks, add it, report before/after")
    add_data_arguments(diagnose, validate_required=True)
    diagnose.add_argument("--rounds", type=round_count, default=4,
                          help="rounds of the residual diagnosis, 1-4 (default 4; ~/refit's diagnose_rounds)")
    diagnose.add_argument("--workers", type=worker_count, default=min(os.cpu_count() or 1, 64),
                          help="processes fitting a round's candidates at once (default: one per CPU; the "
                               "result is the same for any count)")
    diagnose.add_argument("--families", type=family_list, default=None,
                          help="model families compared, comma-separated (default: gpi,gpi_free,two_wire,bouc_wen): gpi, "
                               "gpi_free (its density as free weights), two_wire, two_wire_compact (a compact "
                               "transformation onset), bouc_wen (a baseline); the one "
                               "with the lowest validation error (BIC between those within 5 %%) is written as "
                               "model.yaml")
    diagnose.set_defaults(handler=run_identify_command("run_diagnose"))
    excitation = commands.add_parser("excitation", help="write an identification current signal (t,input CSV)")
    from sma_stage.commands.excitation import add_arguments as excitation_arguments

    excitation_arguments(excitation)
    excitation.set_defaults(handler=run_excitation)
    plot = commands.add_parser("plot", help="draw a recording's loop, time series and residual to PNG")
    plot.add_argument("data", type=Path, metavar="DATA", help="CSV file (t,input,output) or rosbag2 directory")
    plot.add_argument("--model", type=Path, help="model file: its prediction (from rest) and the residual are drawn")
    add_reading_arguments(plot, "current_applied")
    plot.add_argument("--out", type=Path, default=Path("out/plot"), help="folder for the PNGs (default out/plot)")
    plot.add_argument("--json", action="store_true", help="print what was written as JSON")
    plot.set_defaults(handler=run_plot)
    simulate = commands.add_parser("simulate", help="run the stage simulator offline and write a CSV")
    from sma_stage.commands.simulate import add_arguments

    add_arguments(simulate)
    simulate.set_defaults(handler=run_simulate)
    return parser


def add_data_arguments(parser: argparse.ArgumentParser, validate_required: bool) -> None:
    """DATA, --validate and the options that say how to read them, --operators, --out, --json."""
    parser.add_argument("data", type=Path, metavar="DATA", help="CSV file (t,input,output) or rosbag2 directory")
    validation = parser.add_mutually_exclusive_group(required=validate_required)
    validation.add_argument("--validate", type=Path, metavar="DATA", action="append",
                            help="validation data, same form as DATA; give it again for more records (each "
                                 "reported; the model family is chosen on the record it predicts worst)")
    validation.add_argument("--holdout", type=fraction, metavar="FRACTION",
                            help="validate on this last fraction of DATA instead, every model run over all of it "
                                 "(as ~/refit does with its holdout_fraction)")
    parser.add_argument("--operators", type=operator_count, default=None,
                        help="operator count (default: chosen from the data)")
    parser.add_argument("--max-fit-samples", type=sample_budget, default=None,
                        help="fit a longer record on a copy thinned by whole blocks to at most this many samples, "
                             "scored on every sample (default 20000; 0: never thin)")
    add_reading_arguments(parser, "current_cmd")
    parser.add_argument("--out", type=Path, default=Path("out/identification"), help="folder for the results")
    parser.add_argument("--json", action="store_true", help="print the JSON report (and nothing else) on stdout")


def add_reading_arguments(parser: argparse.ArgumentParser, input_topic: str) -> None:
    """How to read DATA: CSV column names, bag topics, joint name, the output's unit."""
    parser.add_argument("--columns", help='CSV column names, e.g. "t=time,input=current,output=pos" (t= for index)')
    parser.add_argument("--input-topic", default=None,
                        help="bag topic of the input (std_msgs/Float64). Default: the current in the output's "
                             "JointState effort, stamped with the position (as the stage node records it), when "
                             f"every message has it; else {input_topic}")
    parser.set_defaults(default_input_topic=input_topic)
    parser.add_argument("--output-topic", default="joint_states", help="bag topic of the output (JointState)")
    parser.add_argument("--joint", default="stage_x", help="joint name in the JointState messages")
    parser.add_argument("--unit", default="m", help="unit of the output column (default m)")


def run_identify_command(name: str):
    """A handler that imports the identification code only when the command runs."""
    def handler(args: argparse.Namespace) -> dict:
        from sma_stage.commands import identify

        return getattr(identify, name)(args)
    return handler


def run_paper(args: argparse.Namespace) -> dict:
    """gpi_tool paper."""
    from sma_stage.commands.paper import evaluate_paper

    report = evaluate_paper(args.out, args.operators)
    if not args.json:
        print((args.out / "paper_summary.md").read_text(encoding="utf-8"))
    return report


def run_excitation(args: argparse.Namespace) -> dict:
    """gpi_tool excitation."""
    from sma_stage.commands.excitation import run_excitation as excitation_command

    report = excitation_command(args)
    if not args.json:
        if "probe_summary" in report:
            print(f"the probe found: {report['probe_summary']}", file=sys.stderr)
        print(f"wrote {report['samples']} samples of the {report['kind']} excitation to {report['file']}",
              file=sys.stderr)
    return report


def run_plot(args: argparse.Namespace) -> dict:
    """gpi_tool plot."""
    from sma_stage.commands.plot import run_plot as plot_command

    report = plot_command(args)
    if not args.json:
        print(f"wrote {', '.join(report['files'])}", file=sys.stderr)
    return report


def run_simulate(args: argparse.Namespace) -> dict:
    """gpi_tool simulate."""
    from sma_stage.commands.simulate import run_simulate as simulate_command

    report = simulate_command(args)
    if not args.json:
        print(f"wrote {report['samples']} samples to {report['file']}", file=sys.stderr)
    return report


class Terminated(KeyboardInterrupt):
    """SIGTERM (kill, timeout, systemd), raised where the command is, so that it ends as Ctrl-C does: its
    worker processes ended, its output folder as it was."""


def _raise_terminated(number: int, frame: object) -> None:
    raise Terminated


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point: run one command; InputError, OSError and MemoryError become one line and exit status 2;
    Ctrl-C and SIGTERM one line and 130 or 143."""
    args = build_parser().parse_args(argv)
    previous = signal.signal(signal.SIGTERM, _raise_terminated) if _in_main_thread() else None
    try:
        return _run(args)
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _in_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def _drop_unraisable(unraisable: object) -> None:
    """sys.unraisablehook after an interrupt: a finalizer's error is not printed."""


def _quiet_teardown() -> None:
    """After Ctrl-C or SIGTERM, the finalizers of objects the interrupt left half-built may raise as they are
    collected (llvmlite's, when it lands while numba loads or compiles a kernel: "Exception ignored in
    ObjectRef.__del__" and a traceback after the one line): such errors are dropped from here on."""
    sys.unraisablehook = _drop_unraisable


def _run(args: argparse.Namespace) -> int:
    try:
        result = args.handler(args)
    except InputError as error:
        print(f"gpi_tool: error: {error}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except OSError as error:
        print(f"gpi_tool: error: {error.strerror or error}: {error.filename or ''}".rstrip(": "), file=sys.stderr)
        return EXIT_BAD_INPUT
    except MemoryError:
        print("gpi_tool: error: out of memory (see docs/reliability.md for the memory a record needs)",
              file=sys.stderr)
        return EXIT_BAD_INPUT
    except Terminated:
        _quiet_teardown()
        print("gpi_tool: terminated", file=sys.stderr)
        return 128 + signal.SIGTERM
    except KeyboardInterrupt:
        _quiet_teardown()
        print("gpi_tool: interrupted", file=sys.stderr)
        return 130
    if getattr(args, "json", False):
        sys.stdout.write(strict_json(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
