"""The launchers' options as flags (``api.arguments.launcher_parameters``): ``--<name-with-dashes>`` for every
parameter of every installed launcher that loads, the generic ones once (``--workers``/``-w``, ``--gpus``,
``--per-gpu``), each typed and bounded as its ``Parameter`` says. They are added when the command parses its flags
(``--help`` included), not when the command line starts: the launchers load only then. The values given reach the
command as ``given(ctx)``: a mapping for the API's ``**launcher_options`` (a list's comma list split)."""

from __future__ import annotations

from typing import Any, Optional

import typer
from typer.core import TyperCommand
from typer.main import _get_param  # Typer's own option builder (pyproject pins typer < 0.30)
from typer.models import ParamMeta

from ..api.arguments import launcher_parameters

KEY = "bronchopose.launcher_options"  # where ``invoke`` leaves the given values (``ctx.meta``)
TYPES = {int: Optional[int], float: Optional[float], bool: Optional[bool]}  # anything else: a string


def option(name: str, param: Any, help: str | None = None) -> Any:
    """The click option of a launcher parameter, built as Typer builds a declared ``typer.Option``."""
    rule = param.rule(name)  # its flag and bounds, as the API checks them
    decls = [rule.flag, *([param.short] if param.short else [])]
    text = help or param.help
    if param.default is not None and help is None and "default" not in text.lower():
        text += f" Default: {','.join(param.default) if isinstance(param.default, list) else param.default}."
    info = typer.Option(None, *decls, help=text, **rule.bounds())
    return _get_param(ParamMeta(name=name, default=info, annotation=TYPES.get(param.type, Optional[str])))


def command(generic_only: bool = False, helps: dict[str, str] | None = None) -> type[TyperCommand]:
    """A command class taking the launchers' options (``generic_only``: the generic ones); ``helps``: its own help
    text of a generic option (``tune``'s ``--workers`` counts trials, not cells)."""

    class LauncherCommand(TyperCommand):
        declared: dict[str, Any] | None = None

        def get_params(self, ctx: Any) -> list[Any]:
            if self.declared is None:
                taken = {p.name for p in self.params}
                self.declared = {n: p for n, p in launcher_parameters(generic_only).items() if n not in taken}
                self.params[:0] = [option(n, p, (helps or {}).get(n)) for n, p in self.declared.items()]
            return super().get_params(ctx)

        def invoke(self, ctx: Any) -> Any:
            given = {n: ctx.params.pop(n, None) for n in self.declared or {}}
            ctx.meta[KEY] = {n: self.declared[n].parse(v) for n, v in given.items() if v is not None}
            return super().invoke(ctx)

    return LauncherCommand


def given(ctx: typer.Context) -> dict[str, Any]:
    """The launcher options given to this command (name -> value; those not given are absent)."""
    return dict(ctx.meta.get(KEY, {}))
