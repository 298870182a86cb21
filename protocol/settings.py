"""One settings layer for every process: pydantic-settings models read from flags, FEDRL_* variables and .env files.

Each process declares its settings once, as a model whose fields are made with :func:`setting` (type, default,
help). Everything else comes from that model: the command-line flags (field ``round_timeout`` is the flag
``--round-timeout`` and the variable ``FEDRL_ROUND_TIMEOUT``; older spellings stay as aliases), the validation, the
one-line errors and the reference ``docs/settings.md`` (``python -m protocol.settings --markdown``).

- Precedence: command line > environment > .env file > default.
- The .env file (KEY=VALUE lines) is ``--env-file PATH`` or ``FEDRL_ENV_FILE``, else ``./.env`` when it exists.
- A bad value is one line on stderr naming the setting, where it came from and the value, and exit code 2.
- A launcher builds its children's settings with :meth:`Settings.child` and hands them over with :func:`to_env`,
  the one function that turns a model back into variables.

Models live next to their process (``chief/settings.py``, ``worker/settings.py``, ...); this module holds only the
machinery and the MQTT settings every client shares, so that torch-free processes (chief, bridge) can import it.
"""

from __future__ import annotations

import argparse
import functools
import importlib
import os
import re
import sys
import types
import typing
from collections.abc import Callable, Iterable, Mapping, Sequence
from contextvars import ContextVar
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal, NoReturn, Protocol, TypeVar, cast

from dotenv import dotenv_values
from pydantic import (
    BeforeValidator,
    Field,
    GetCoreSchemaHandler,
    PositiveInt,
    PrivateAttr,
    ValidationError,
    field_validator,
)
from pydantic.fields import FieldInfo
from pydantic_core import PydanticUndefined, core_schema
from pydantic_settings import (
    BaseSettings,
    DotEnvSettingsSource,
    EnvSettingsSource,
    NoDecode,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
)

from protocol.mqtt import DEFAULT_BROKER, BrokerAddress
from protocol.tasks import TASKS
from protocol.topics import check_id

ENV_PREFIX = "FEDRL_"
ENV_FILE_VAR = "FEDRL_ENV_FILE"
DEFAULT_ENV_FILE = ".env"

S = TypeVar("S", bound="Settings")


# -- declaring settings ------------------------------------------------------------------------------------------


def setting(default: Any = PydanticUndefined, help: str = "", *, aliases: Sequence[str] = (), env: bool = True,
            flag: bool = True, positional: bool = False, append: bool = False, metavar: str | None = None,
            **constraints: Any) -> Any:
    """A settings field: its default, its help, and how it is reached.

    ``aliases`` are further flags (older spellings) beside the one derived from the field's name; ``env=False``
    makes it a flag only, ``flag=False`` a variable only (secrets); ``positional`` and ``append`` (a repeatable
    flag) shape the command line. ``constraints`` go to pydantic's ``Field`` (``ge=1``, ...).
    """
    extra = {"aliases": list(aliases), "env": env, "flag": flag, "positional": positional, "append": append,
             "metavar": metavar}
    return Field(default, description=help, json_schema_extra=cast(Any, extra), **constraints)


@dataclass(frozen=True)
class OneOf:
    """``Annotated`` marker: the value must be one of ``options()`` (a registry, read when validating)."""

    options: Callable[[], Iterable[str]]

    def __get_pydantic_core_schema__(self, source: Any, handler: GetCoreSchemaHandler) -> core_schema.CoreSchema:
        return core_schema.no_info_after_validator_function(self.check, handler(source))

    def check(self, value: Any) -> Any:
        options = list(self.options())
        if value is not None and value not in options:
            raise ValueError(f"invalid choice {value!r}; choose from {', '.join(options)}")
        return value


def _words(value: Any) -> Any:
    """``"a,b c"`` or ``["a,b", "c"]`` -> ``["a", "b", "c"]``: a list from a variable or from words after a flag."""
    if isinstance(value, str):
        return [w for w in re.split(r"[,\s]+", value) if w]
    if isinstance(value, list):
        return [w for item in value for w in (_words(item) if isinstance(item, str) else [item])]
    return value


#: A task of protocol/tasks.py.
TaskName = Annotated[str, OneOf(lambda: sorted(TASKS))]
#: A list given as ``a,b,c`` (or spaces) in a variable and as separate words on the command line.
Words = Annotated[list[str], NoDecode, BeforeValidator(_words)]
Counts = Annotated[list[PositiveInt], NoDecode, BeforeValidator(_words), Field(min_length=1)]
Port = Annotated[int, Field(ge=0, le=65535)]
LogLevel = Annotated[str, OneOf(lambda: ["DEBUG", "INFO", "WARNING", "ERROR"]), BeforeValidator(str.upper)]


def _meta(field: FieldInfo) -> dict[str, Any]:
    extra = field.json_schema_extra if isinstance(field.json_schema_extra, dict) else {}
    return {"aliases": [], "env": True, "flag": True, "positional": False, "append": False, "metavar": None,
            **extra}


def env_name(name: str, field: FieldInfo) -> str | None:
    """The variable of field ``name`` (``FEDRL_<NAME>``), or None for a flag-only setting."""
    return ENV_PREFIX + name.upper() if _meta(field)["env"] else None


def flags(name: str, field: FieldInfo) -> list[str]:
    """The flags of field ``name``: ``--the-name`` and its aliases (empty for a variable-only setting)."""
    meta = _meta(field)
    if not meta["flag"]:
        return []
    if meta["positional"]:
        return [name]
    return ["--" + name.replace("_", "-"), *(a for a in meta["aliases"] if a != "--" + name.replace("_", "-"))]


def _bare(annotation: Any) -> Any:
    """``int | None`` -> ``int``; ``Annotated[X, ...]`` -> ``X``."""
    while typing.get_origin(annotation) is Annotated:
        annotation = typing.get_args(annotation)[0]
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        if len(args) == 1:
            return _bare(args[0])
    return annotation


def _markers(annotation: Any) -> list[Any]:
    """The ``Annotated`` metadata anywhere in ``annotation`` (``Annotated[str, OneOf(...)] | None``)."""
    found: list[Any] = []
    if typing.get_origin(annotation) is Annotated:
        found += list(annotation.__metadata__)
    for arg in typing.get_args(annotation):
        found += _markers(arg)
    return found


def choices(field: FieldInfo) -> list[str] | None:
    """The allowed values of a field (a ``Literal`` or :class:`OneOf`), or None."""
    for item in [*field.metadata, *_markers(field.annotation)]:
        if isinstance(item, OneOf):
            return list(item.options())
    bare = _bare(field.annotation)
    if typing.get_origin(bare) is Literal:
        return [str(a) for a in typing.get_args(bare)]
    return None


def type_name(field: FieldInfo) -> str:
    """A short name of a field's type for help and docs."""
    bare = _bare(field.annotation)
    if choices(field) is not None:
        return "choice"
    if typing.get_origin(bare) is list:
        return f"list of {_bare(typing.get_args(bare)[0]).__name__}"
    return {Path: "path"}.get(bare, getattr(bare, "__name__", str(bare)))


def _metavar(field: FieldInfo) -> str:
    bare = _bare(field.annotation)
    if typing.get_origin(bare) is list:
        bare = _bare(typing.get_args(bare)[0])
    return {int: "INT", float: "NUM", Path: "PATH"}.get(bare, "TEXT")


def _is_bool(field: FieldInfo) -> bool:
    return _bare(field.annotation) is bool


def _is_list(field: FieldInfo) -> bool:
    return typing.get_origin(_bare(field.annotation)) is list


def encode(value: Any) -> str:
    """A JSON-mode value as a variable's text: None is empty (unset), lists are comma-separated."""
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, list):
        return ",".join(encode(v) for v in value)
    return str(value)


# -- the base model ----------------------------------------------------------------------------------------------


#: Set while a model is built from given values and defaults only (Settings.child with inherit=False).
_ONLY_GIVEN: ContextVar[bool] = ContextVar("_ONLY_GIVEN", default=False)


class _EnvGate:
    """Sources skip the flag-only fields (``setting(env=False)``)."""

    def get_field_value(self, field: FieldInfo, field_name: str) -> tuple[Any, str, bool]:
        if not _meta(field)["env"]:
            return None, field_name, False
        return super().get_field_value(field, field_name)  # type: ignore[misc]


class _Env(_EnvGate, EnvSettingsSource):
    pass


class _DotEnv(_EnvGate, DotEnvSettingsSource):
    pass


class Settings(BaseSettings):
    """Base of every process's settings; see the module docstring."""

    model_config = SettingsConfigDict(env_prefix=ENV_PREFIX, env_file=DEFAULT_ENV_FILE, env_ignore_empty=True,
                                      extra="ignore", dotenv_filtering="only_existing")

    #: Flags and variables that name the .env file (the bridge adds its older --config / FEDRL_BRIDGE_CONFIG).
    env_file_flags: ClassVar[tuple[str, ...]] = ("--env-file",)
    env_file_vars: ClassVar[tuple[str, ...]] = (ENV_FILE_VAR,)

    _prog: str = PrivateAttr(default="fedrl")
    _env_file: Path | None = PrivateAttr(default=None)

    @classmethod
    def settings_customise_sources(cls, settings_cls: type[BaseSettings], init_settings: PydanticBaseSettingsSource,
                                   env_settings: PydanticBaseSettingsSource,
                                   dotenv_settings: PydanticBaseSettingsSource,
                                   file_secret_settings: PydanticBaseSettingsSource,
                                   ) -> tuple[PydanticBaseSettingsSource, ...]:
        if _ONLY_GIVEN.get():
            return (init_settings,)
        env_file = getattr(dotenv_settings, "env_file", None)
        return init_settings, _Env(settings_cls), _DotEnv(settings_cls, env_file=env_file)

    # -- reading -------------------------------------------------------------------------------------------------

    @classmethod
    def parser(cls, prog: str, description: str | None = None, epilog: str | None = None) -> argparse.ArgumentParser:
        """The command line of this model: one flag per field (its default left to the model)."""
        parser = _OneLineParser(prog=prog, description=description or (cls.__doc__ or "").strip(), epilog=epilog)
        parser.add_argument(*cls.env_file_flags, dest="env_file", metavar="PATH", default=argparse.SUPPRESS,
                            help=f"read FEDRL_* settings from this KEY=VALUE file (env {', '.join(cls.env_file_vars)}"
                            f"; default ./{DEFAULT_ENV_FILE} where it exists; the environment wins over it)")
        for name, field in cls.model_fields.items():
            names = flags(name, field)
            if not names:
                continue
            meta = _meta(field)
            kwargs: dict[str, Any] = {"default": argparse.SUPPRESS, "help": _help(name, field).replace("%", "%%")}
            options = choices(field)
            if meta["positional"]:
                kwargs["metavar"] = meta["metavar"] or name.upper()
                if not field.is_required():
                    kwargs["nargs"] = "?"
                parser.add_argument(*names, **kwargs)
                continue
            kwargs["dest"] = name
            if _is_bool(field):
                kwargs["action"] = argparse.BooleanOptionalAction
            else:
                kwargs["metavar"] = meta["metavar"] or ("{" + ",".join(options) + "}" if options else _metavar(field))
                if _is_list(field):
                    kwargs["action" if meta["append"] else "nargs"] = "append" if meta["append"] else "+"
            parser.add_argument(*names, **kwargs)
        return parser

    @classmethod
    def load(cls: type[S], argv: Sequence[str] | None = None, *, prog: str, description: str | None = None,
             epilog: str | None = None) -> S:
        """Settings from ``argv`` (default: sys.argv[1:]), the environment, the .env file and the defaults.

        ``--help`` prints the options once the environment and .env file have been checked. A bad value anywhere
        is one line on stderr and SystemExit(2).
        """
        prog = program(prog)
        argv = list(sys.argv[1:] if argv is None else argv)
        parser = cls.parser(prog, description, epilog)
        pre = _OneLineParser(prog=prog, add_help=False, allow_abbrev=False)
        pre.add_argument(*cls.env_file_flags, dest="env_file", default=None)
        pre.add_argument("-h", "--help", action="store_true")
        early, _ = pre.parse_known_args(argv)
        env_file = cls._env_file_path(prog, early.env_file)
        if early.help:
            cls._build(prog, env_file, {}, ignore_missing=True)
            parser.print_help()
            raise SystemExit(0)
        given = vars(parser.parse_args(argv))
        given.pop("env_file", None)
        return cls._build(prog, env_file, given, argv=argv)

    @classmethod
    def _env_file_path(cls, prog: str, flag_value: str | None) -> Path:
        named = [(flag_value, f"{cls.env_file_flags[0]} {flag_value}")] if flag_value else []
        named += [(os.environ[v], f"{v}={os.environ[v]}") for v in cls.env_file_vars if os.environ.get(v)]
        if not named:
            return Path(DEFAULT_ENV_FILE)
        path, where = Path(named[0][0]).expanduser(), named[0][1]
        if not path.exists() or path.is_dir():  # /dev/null is fine: no settings
            fail(prog, f"bad setting {where}: no such file")
        try:
            path.open("rb").close()
        except OSError as err:
            fail(prog, f"bad setting {where}: cannot read it: {err.strerror or err}")
        return path

    @classmethod
    def _build(cls: type[S], prog: str, env_file: Path, given: Mapping[str, Any], *, given_by: str = "command line",
               ignore_missing: bool = False, argv: Sequence[str] = ()) -> S:
        try:
            settings = cls(_env_file=env_file, **given)
        except ValidationError as err:
            errors = [e for e in err.errors() if not (ignore_missing and e["type"] == "missing")]
            if not errors:
                return cast(S, cls.model_construct())
            fail(prog, cls._describe(errors, env_file, given, given_by, argv))
        settings._prog, settings._env_file = prog, env_file
        return settings

    @classmethod
    def _describe(cls, errors: list[Any], env_file: Path, given: Mapping[str, Any], given_by: str,
                  argv: Sequence[str]) -> str:
        """The first error as ``bad setting <where it came from>: <reason>``."""
        first = errors[0]
        reason = re.sub(r"^(Value|Assertion) error, ", "", first["msg"])
        reason = reason[:1].lower() + reason[1:]
        more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
        name = first["loc"][0] if first["loc"] else None
        if name not in cls.model_fields:
            return f"{reason}{more}"
        field = cls.model_fields[name]
        var, names = env_name(name, field), flags(name, field)
        if name in given:
            value = given[name]
            shown = " ".join(map(str, value)) if isinstance(value, list) else str(value)
            typed = [n for n in names if any(a == n or a.startswith(n + "=") for a in argv)]
            where = f"{(typed or names or [name])[0]} {shown!r} ({given_by})"
        elif var and os.environ.get(var):
            where = f"{var}={os.environ[var]!r} (environment)"
        elif var and env_file.is_file() and (dotenv_values(env_file).get(var) or ""):
            where = f"{var}={dotenv_values(env_file)[var]!r} (.env file {env_file})"
        else:
            where = f"{names[0] if names else var or name} (default {field.default!r})"
        return f"bad setting {where}: {reason}{more}"

    # -- handing on ----------------------------------------------------------------------------------------------

    def child(self, cls: type[S], *, inherit: bool = True, **values: Any) -> S:
        """The settings of a process this one starts: the fields ``cls`` shares with these, then ``values``; the
        rest as the child would read them (this environment and .env file), or with ``inherit=False`` (a container,
        which sees nothing of this host) the defaults. A bad value exits as :meth:`load` does."""
        shared = {name: getattr(self, name) for name in cls.model_fields if name in type(self).model_fields}
        env_file = self._env_file or Path(DEFAULT_ENV_FILE)
        token = _ONLY_GIVEN.set(not inherit)
        try:
            return cls._build(self._prog, env_file, {**shared, **values}, given_by="set by the launcher")
        finally:
            _ONLY_GIVEN.reset(token)


def to_env(settings: Settings) -> dict[str, str]:
    """Every setting as the FEDRL_* variables a child process reads back into the same model."""
    data = settings.model_dump(mode="json")
    fields = type(settings).model_fields
    return {var: encode(data[name]) for name, field in fields.items() if (var := env_name(name, field))}


def fail(prog: str, message: str) -> NoReturn:
    """One line on stderr, exit code 2."""
    print(f"{prog}: {message}", file=sys.stderr)
    raise SystemExit(2)


class EntryPoint(Protocol):
    """A process's ``main``: its command line (None: ``sys.argv``) in, its exit code out."""

    def __call__(self, argv: list[str] | None = None) -> int: ...


def returns_code(main: EntryPoint) -> EntryPoint:
    """Make an entry point return its exit code instead of raising SystemExit (``--help``: 0, a bad setting: 2),
    so that tests and console scripts (``sys.exit(main())``) see the same int."""

    @functools.wraps(main)
    def wrapper(argv: list[str] | None = None) -> int:
        try:
            return main(argv)
        except SystemExit as stop:
            if isinstance(stop.code, str):
                print(stop.code, file=sys.stderr)
            return stop.code if isinstance(stop.code, int) else (0 if stop.code is None else 1)

    return wrapper


def program(default: str) -> str:
    """The name to report under: the console script's (``fedrl-chief``) when run as one, else ``default``."""
    name = Path(sys.argv[0]).name if sys.argv and sys.argv[0] else ""
    return name if name.startswith("fedrl-") else default


class _OneLineParser(argparse.ArgumentParser):
    """An option error is one line on stderr and exit code 2 (no usage dump)."""

    def error(self, message: str) -> NoReturn:
        fail(self.prog, f"{message} (--help lists the options)")


def _help(name: str, field: FieldInfo) -> str:
    """The field's help with its variable and default: ``... (env FEDRL_X, default 30)``."""
    notes = []
    if var := env_name(name, field):
        notes.append(f"env {var}")
    if not field.is_required() and field.default is not None and field.default != []:
        default = encode(field.default) if not isinstance(field.default, Path) else str(field.default)
        notes.append(f"default {default or repr('')}")
    return f"{field.description} ({', '.join(notes)})" if notes else field.description or ""


# -- settings every MQTT client shares -----------------------------------------------------------------------------


class MqttSettings(Settings):
    """Where the broker is, how to log in, and how loud to log."""

    broker: str = setting(DEFAULT_BROKER, "broker URL mqtt://[user:pass@]host:port, or mqtts:// for TLS")
    mqtt_username: str | None = setting(None, "broker user name (make-users.sh writes one per process)")
    mqtt_password: str | None = setting(None, "broker password (a variable only: flags show in the process list)",
                                        flag=False)
    mqtt_ca_file: Path | None = setting(None, "CA certificate of a TLS broker")
    max_payload: int | None = setting(None, "bytes; larger messages travel in chunks (e.g. 131072 for AWS IoT "
                                      "Core's 128 KB cap); 0 or unset: no chunking")
    log_level: LogLevel = setting("INFO", "DEBUG, INFO, WARNING or ERROR")

    @field_validator("broker")
    @classmethod
    def _broker_parses(cls, value: str) -> str:
        BrokerAddress.parse(value)
        return value

    @field_validator("max_payload")
    @classmethod
    def _payload(cls, value: int | None) -> int | None:
        if value is not None and value != 0 and value < 1024:
            raise ValueError("must be at least 1024 bytes (or 0 for no chunking)")
        return value or None

    def address(self) -> BrokerAddress:
        """The broker with these credentials (explicit ones win over those in the URL)."""
        return BrokerAddress.parse(self.broker, username=self.mqtt_username, password=self.mqtt_password,
                                   ca_file=str(self.mqtt_ca_file) if self.mqtt_ca_file else None)


class RunMqttSettings(MqttSettings):
    """An MQTT client of one run (topic prefix fedrl/<run>/)."""

    run_id: str = setting("default", "run name, the topic prefix fedrl/<run>/")

    @field_validator("run_id")
    @classmethod
    def _run_id(cls, value: str) -> str:
        return check_id(value, "run id")


# -- the reference -------------------------------------------------------------------------------------------------

#: Every entry point: (command, console script, its settings model by import path). Imported only to write the
#: reference, so that this package imports none of them.
PROCESSES: tuple[tuple[str, str, str], ...] = (
    ("python -m deploy.run_local", "fedrl-run", "deploy.settings:LocalRunSettings"),
    ("python -m chief", "fedrl-chief", "chief.settings:ChiefSettings"),
    ("python -m worker", "fedrl-worker", "worker.settings:WorkerSettings"),
    ("python -m services.broker", "fedrl-broker", "services.broker.settings:BrokerSettings"),
    ("python -m services.dashboard", "fedrl-dashboard", "services.dashboard.settings:DashboardSettings"),
    ("python -m services.qube_sim", "fedrl-sim-rig", "services.qube_sim.settings:SimRigSettings"),
    ("python -m rpi_bridge", "fedrl-bridge", "rpi_bridge.settings:BridgeSettings"),
    ("python -m worker.evaluate", "fedrl-evaluate", "worker.settings:EvaluateSettings"),
    ("python -m worker.train_local", "fedrl-train-local", "worker.settings:TrainLocalSettings"),
    ("python -m deploy.inprocess", "fedrl-inprocess", "deploy.settings:InprocessSettings"),
    ("python -m deploy.docker", "fedrl-docker", "deploy.settings:DockerSettings"),
)


def model_of(path: str) -> type[Settings]:
    module, _, name = path.partition(":")
    return getattr(importlib.import_module(module), name)


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def markdown_table(cls: type[Settings]) -> str:
    """One row per setting: flag(s), variable, type, default, help."""
    rows = ["| flag | variable | type | default | help |", "| --- | --- | --- | --- | --- |"]
    for name, field in cls.model_fields.items():
        names = ", ".join(f"`{f}`" for f in flags(name, field)) or "-"
        var = f"`{v}`" if (v := env_name(name, field)) else "-"
        options = choices(field)
        kind = type_name(field) + (": " + ", ".join(f"`{c}`" for c in options) if options else "")
        if field.is_required():
            default = "required"
        elif field.default is None or field.default == []:
            default = "unset"
        else:
            default = f"`{encode(field.default) if not isinstance(field.default, Path) else field.default}`"
        rows.append(f"| {names} | {var} | {_cell(kind)} | {_cell(default)} | {_cell(field.description or '')} |")
    return "\n".join(rows)


def markdown() -> str:
    """docs/settings.md: every process's settings."""
    parts = [
        "# Settings reference",
        "",
        "<!-- generated by `python -m protocol.settings --markdown > docs/settings.md`; a test keeps it up to "
        "date -->",
        "",
        "Every process reads its settings from, in this order of precedence: its command-line flags, `FEDRL_*` "
        "environment variables, a `.env` file (KEY=VALUE lines: `--env-file PATH` or `FEDRL_ENV_FILE`, else "
        "`./.env` where it exists), and the defaults below. A flag's variable is `FEDRL_` and the field's name "
        "in capitals (`--round-timeout`: `FEDRL_ROUND_TIMEOUT`); older flag spellings are kept as aliases. A bad "
        "value is one line on stderr naming the setting, where it came from and the value, and exit code 2. Lists "
        "are comma-separated in a variable, separate words after a flag; booleans also take `--no-<flag>`.",
        "",
    ]
    for command, script, path in PROCESSES:
        cls = model_of(path)
        doc = (cls.__doc__ or "").strip().splitlines()[0]
        files = ", ".join(f"`{f}`" for f in (*cls.env_file_flags, *cls.env_file_vars))
        parts += [f"## `{script}` (`{command}`)", "", f"{doc} The .env file: {files}.", "", markdown_table(cls), ""]
    return "\n".join(parts)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m protocol.settings", description="The settings reference.")
    parser.add_argument("--markdown", action="store_true", help="print docs/settings.md")
    args = parser.parse_args(argv)
    if not args.markdown:
        parser.print_help()
        return 0
    sys.stdout.write(markdown())
    return 0


if __name__ == "__main__":
    from protocol import settings as module  # the models import that module, not this __main__ copy of it

    sys.exit(module.main())
