"""What every command shares: one-line errors with exit status 2, device choice, output flags."""

from __future__ import annotations

import signal
import sys
from collections.abc import Callable

import click
from click.core import ParameterSource
from rich.markup import escape

from dbb_capture.core.errors import DbbError
from dbb_capture.core.progress import console


_TERMINATED = []


def _on_sigterm(signum, frame) -> None:
    # SIGTERM (timeout, CI, docker stop) stops a command the way Ctrl-C does: every output's
    # scratch is removed and the trainers save their checkpoint on the way out.
    _TERMINATED.append(signum)
    raise KeyboardInterrupt


class _OneLineErrors:
    """Usage errors and :class:`DbbError` end in one red line and exit 2; Ctrl-C and SIGTERM
    stop cleanly with one line (exit 130 and 143)."""

    def main(self, args=None, prog_name=None, **extra):  # noqa: D102 - click API
        if signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
            signal.signal(signal.SIGTERM, _on_sigterm)
        try:
            rv = super().main(args=args, prog_name=prog_name, standalone_mode=False, **extra)
        except (click.exceptions.Abort, KeyboardInterrupt):
            if _TERMINATED:
                console.print("[red]stopped[/red] (SIGTERM)")
                sys.exit(143)
            console.print("[red]aborted[/red]")
            sys.exit(130)
        except click.ClickException as e:
            # click's own format spans several lines (usage, hint, error): users asked for one.
            ctx = getattr(e, "ctx", None)
            where = ctx.command_path if ctx is not None else (prog_name or self.name)
            console.print(f"[red]error:[/red] {escape(f'{where}: {e.format_message()}')}", soft_wrap=True)
            sys.exit(2)
        except DbbError as e:
            console.print(f"[red]error:[/red] {escape(e.worded(self._flag_words(args)))}", soft_wrap=True)
            sys.exit(2)
        if isinstance(rv, int) and rv != 0:
            sys.exit(rv)
        sys.exit(0)

    def _flag_words(self, args) -> Callable[[str], str]:
        """How this command words the library's settings: as its own option (``crop_size`` ->
        ``--crop-size``) where the command has one, else by the setting's name."""
        argv = list(sys.argv[1:] if args is None else args)
        cmd = self._command_of(argv)
        flags = {p.name: p.opts[0] for p in (cmd.params if cmd else []) if isinstance(p, click.Option)}
        return lambda name: flags.get(name, name)


class DbbGroup(_OneLineErrors, click.Group):
    """A click group of commands with one-line errors (exit status 2)."""

    def _command_of(self, argv: list[str]) -> click.Command | None:
        return next((self.commands[a] for a in argv if a in self.commands), None)


class DbbCommand(_OneLineErrors, click.Command):
    """A single click command with one-line errors (exit status 2)."""

    def _command_of(self, argv: list[str]) -> click.Command:
        return self


def typed(*names: str) -> list[str]:
    """The parameters among ``names`` (click parameter names) typed on the running command's
    line, in the command's order."""
    ctx = click.get_current_context()
    return [p.name for p in ctx.command.params
            if p.name in names and ctx.get_parameter_source(p.name) is ParameterSource.COMMANDLINE]


def given(*names: str) -> list[str]:
    """:func:`typed`, spelled as typed (``--no-clean-plate`` for a switch turned off)."""
    ctx = click.get_current_context()
    params = {p.name: p for p in ctx.command.params}
    out = []
    for n in typed(*names):
        p = params[n]
        off = isinstance(p, click.Option) and p.secondary_opts and ctx.params[n] is False
        out.append((p.secondary_opts if off else p.opts)[0])
    return out


def refuse_with(flags: list[str], why: str) -> None:
    """One line (exit 2) when any of ``flags`` was given: "``--a``, ``--b``: <why>"."""
    if flags:
        raise click.UsageError(f"{', '.join(flags)}: {why}")


def refuse_resume_overwrite(resume: bool, overwrite: bool) -> None:
    """A trainer's ``--resume`` continues RUN, ``--overwrite`` throws it away: never both."""
    if resume and overwrite:
        raise click.UsageError("--resume continues RUN and --overwrite replaces it: give one of them")


overwrite_option = click.option(
    "--overwrite", is_flag=True, help="Replace the output if it already exists.")
