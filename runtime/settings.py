"""One settings layer for every process: pydantic-settings models read from flags, FEDRL_* variables and .env files.

Each process declares its settings once, as a model whose fields are made with :func:`setting` (type, default,
help). Everything else comes from that model: the command-line flags (field ``round_timeout`` is the flag
``--round-timeout`` and the variable ``FEDRL_ROUND_TIMEOUT``; older spellings stay as aliases), the validation, the
one-line errors and the reference ``docs/settings.md`` (``python -m deploy.reference --markdown``).

- Precedence: command line > environment > .env file > default.
- The .env file (KEY=VALUE lines) is ``--env-file PATH`` or ``FEDRL_ENV_FILE``, else ``./.env`` when it exists.
- The flags are pydantic-settings' own (``CliSettingsSource``, on a parser whose errors are one line).
- A bad value is one line on stderr naming the setting, where it came from and the value, and exit code 2.
- A launcher builds its children's settings with :meth:`Settings.child` and hands them over with :func:`to_env`,
  the one function that turns a model back into variables.

Models live next to their process (``chief/settings.py``, ``worker/settings.py``, ...); this module holds only the
machinery and the MQTT settings every client shares, so that torch-free processes (chief, bridge) can import it.
"""

from __future__ import annotations

import argparse
import difflib
import functools
import os
import re
import sys
import typing
from collections.abc import Callable, Iterable, Mapping, Sequence
from contextvars import ContextVar
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, ClassVar, NoReturn, Protocol, Self, TypeVar, cast

from dotenv import dotenv_values
from pydantic import (
    BeforeValidator,
    Field,
    GetCoreSchemaHandler,
    PositiveInt,
    PrivateAttr,
    ValidationError,
    field_validator,
    model_validator,
)
from pydantic.fields import FieldInfo
from pydantic_core import PydanticUndefined, core_schema
from pydantic_settings import (
    CLI_SUPPRESS,
    BaseSettings,
    CliPositionalArg,
    CliSettingsSource,
    CliSuppress,
    DotEnvSettingsSource,
    EnvSettingsSource,
    NoDecode,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
    SettingsError,
)

from protocol import learners, qube
from protocol.auth import key_bytes
from protocol.mqtt import DEFAULT_BROKER, BrokerAddress
from protocol.tasks import TASKS
from protocol.topics import check_id
from protocol.transport import Connect, connector, transport_of

ENV_PREFIX = "FEDRL_"
ENV_FILE_VAR = "FEDRL_ENV_FILE"
DEFAULT_ENV_FILE = ".env"

S = TypeVar("S", bound="Settings")


# -- declaring settings ------------------------------------------------------------------------------------------


def setting(default: Any = PydanticUndefined, help: str = "", *, aliases: Sequence[str] = (), env: bool = True,
            metavar: str | None = None, **constraints: Any) -> Any:
    """A settings field: its default, its help, and how it is reached.

    ``aliases`` are further flags (older spellings) beside ``--the-name`` that pydantic-settings derives from the
    field's name; ``env=False`` makes it a flag only. A variable-only setting (a secret) is typed
    ``CliSuppress[...]``, a positional argument ``CliPositionalArg[...]`` (pydantic-settings' markers). A
    ``CliSuppress`` list with ``aliases`` is a repeatable flag whose every value is one item, taken whole
    (``--set KEY=VALUE``; ``metavar`` names it). ``constraints`` go to pydantic's ``Field`` (``ge=1``, ...).
    """
    extra = {"aliases": list(aliases), "env": env, "metavar": metavar}
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
LearnerName = Annotated[str, OneOf(learners.names)]


#: An action set of the QUBE tasks (protocol/qube.py ACTION_SETS).
QubeActions = Annotated[str, OneOf(lambda: list(qube.ACTION_SETS))]


def qube_actions_setting() -> Any:
    """The ``qube_actions`` setting, the same in every process that builds or checks a QUBE task."""
    return setting(qube.DEFAULT_ACTIONS, "--env qube/qube-local: the action set: paper (the paper's three actions of "
                   "+-60 counts), levels (nine up to +-150 counts) or voltage (continuous up to +-150 counts; not "
                   "DQN); docs/explanation/qube-actions.md")


def warm_lr_setting(default: float = 1.0) -> Any:
    """The ``warm_lr`` setting, the same in the worker and in every launcher that warm-starts one."""
    return setting(default, "with --init-model: the learning rates' factor, except after 3 episodes in a row short "
                   "of TC, which take the learner's own (worker/federated.py warm_factor, docs/how-to/lab.md); 1: the "
                   "learner's rates throughout", gt=0, le=1)


def warm_temperature_setting(default: float = 1.0) -> Any:
    """The ``warm_temperature`` setting, the same in the worker and in every launcher that warm-starts one."""
    return setting(default, "with --init-model and PPO: the policy's temperature at the start, its action logits "
                   "divided by it (a Gaussian's standard deviation times it), so that the model samples closer to its "
                   "greedy action; it learns on from there (worker/ppo.py temper, docs/how-to/warm-start.md); 1: as "
                   "the model was trained", gt=0, le=1)


def warm_start_problem(init_model: object, warm_lr: float = 1.0, warm_temperature: float = 1.0,
                       algo: str = learners.DEFAULT) -> str | None:
    """Why a warm start's settings cannot be given (for the settings' validators): they need --init-model, and a
    temperature a learner that has one."""
    for name, value in (("warm_lr", warm_lr), ("warm_temperature", warm_temperature)):
        if value != 1.0 and init_model is None:
            flag, var = "--" + name.replace("_", "-"), "FEDRL_" + name.upper()
            return f"{flag} ({var}) is a setting of a warm start: give --init-model too"
    return temperature_problem(warm_temperature, algo)


def temperature_problem(warm_temperature: float, algo: str = learners.DEFAULT) -> str | None:
    """Why a warm start's policy temperature cannot be given to learner ``algo`` (None: it can)."""
    if warm_temperature != 1.0 and algo not in learners.TEMPERED:
        return (f"--warm-temperature (FEDRL_WARM_TEMPERATURE) needs a learner with a policy temperature "
                f"({', '.join(learners.TEMPERED)}), not {algo}")
    return None


def fits_task(algo: str, env: str, qube_actions: str | None = None) -> None:
    """A ValueError when learner ``algo`` cannot act in task ``env``'s action space (for the settings' validators:
    refused with one line before a process starts, not by a worker that dies while its chief waits)."""
    if (problem := learners.misfit(algo, env, qube_actions)) is not None:
        raise ValueError(problem)


#: A list given as ``a,b,c`` (or spaces) in a variable and as separate words on the command line.
Words = Annotated[list[str], NoDecode, BeforeValidator(_words)]


def _assignments(value: Any) -> Any:
    """``"a=1,b=(2, 3)"`` -> ``["a=1", "b=(2, 3)"]``: a variable's KEY=VALUE items, split at the commas that start
    another ``KEY=`` (a value may hold commas of its own: a tuple)."""
    if isinstance(value, str):
        return [item.strip() for item in re.split(r",\s*(?=[A-Za-z_]\w*=)", value) if item.strip()]
    return value


#: KEY=VALUE items (``--set KEY=VALUE``, repeatable; a variable's are comma-separated: :func:`encode` joins them so).
Assignments = Annotated[list[str], NoDecode, BeforeValidator(_assignments)]
Counts = Annotated[list[PositiveInt], NoDecode, BeforeValidator(_words), Field(min_length=1)]
Port = Annotated[int, Field(ge=0, le=65535)]
LogLevel = Annotated[str, OneOf(lambda: ["DEBUG", "INFO", "WARNING", "ERROR"]), BeforeValidator(str.upper)]


def _meta(field: FieldInfo) -> dict[str, Any]:
    extra = field.json_schema_extra if isinstance(field.json_schema_extra, dict) else {}
    return {"aliases": [], "env": True, "metavar": None, **extra}


def env_name(name: str, field: FieldInfo) -> str | None:
    """The variable of field ``name`` (``FEDRL_<NAME>``), or None for a flag-only setting."""
    return ENV_PREFIX + name.upper() if _meta(field)["env"] else None


#: The marker of CliPositionalArg, as it appears in a field's metadata.
_POSITIONAL = typing.get_args(CliPositionalArg[int])[1]


def flags(name: str, field: FieldInfo) -> list[str]:
    """The command line of field ``name``: ``--the-name`` (as pydantic-settings derives it) and its aliases, the
    name of a positional argument, a repeatable flag's own names, or nothing for a variable-only setting."""
    aliases = _meta(field)["aliases"]
    if CLI_SUPPRESS in field.metadata:
        return aliases
    return [name] if _POSITIONAL in field.metadata else ["--" + name.replace("_", "-"), *aliases]


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
    def parser(cls, prog: str, description: str | None = None,
               epilog: str | None = None) -> tuple[argparse.ArgumentParser, CliSettingsSource[Any]]:
        """The command line of this model, as pydantic-settings derives it from the fields (``--the-name``,
        ``--no-the-name`` for a boolean), with ``--env-file`` and the repeatable flags (see :func:`setting`)."""
        parser = _OneLineParser(prog=prog, description=description or (cls.__doc__ or "").strip(), epilog=epilog)
        parser.add_argument(*cls.env_file_flags, dest="env_file", metavar="PATH", default=argparse.SUPPRESS,
                            help=f"read FEDRL_* settings from this KEY=VALUE file (env {', '.join(cls.env_file_vars)}"
                            f"; default ./{DEFAULT_ENV_FILE} where it exists; the environment wins over it)")
        shortcuts: dict[str, str | list[str]] = {}
        for name, field in cls.model_fields.items():
            names = flags(name, field)
            if CLI_SUPPRESS not in field.metadata:
                shortcuts[name.replace("_", "-")] = [a.lstrip("-") for a in names[1:]]
            elif names:  # a repeatable flag, its values taken whole
                var = env_name(name, field)
                parser.add_argument(*names, dest=name, action="append", default=argparse.SUPPRESS,
                                    metavar=_meta(field)["metavar"], help=f"{field.description} (repeatable)"
                                    + (f" [env: {var}]" if var else ""))
        source: CliSettingsSource[Any] = CliSettingsSource(
            cls, root_parser=parser, cli_kebab_case=True, cli_implicit_flags=True, cli_avoid_json=True,
            cli_hide_none_type=True, cli_show_env_vars=True, cli_shortcuts=shortcuts, _env_settings_source=_Env(cls),
            add_argument_method=lambda parser, *names, **kwargs: _add_argument(cls, parser, *names, **kwargs))
        return parser, source

    @classmethod
    def load(cls: type[S], argv: Sequence[str] | None = None, *, prog: str, description: str | None = None,
             epilog: str | None = None) -> S:
        """Settings from ``argv`` (default: sys.argv[1:]), the environment, the .env file and the defaults.

        ``--help`` prints the options once the environment and .env file have been checked. A bad value anywhere
        is one line on stderr and SystemExit(2).
        """
        prog = program(prog)
        argv = list(sys.argv[1:] if argv is None else argv)
        parser, source = cls.parser(prog, description, epilog)
        pre = _OneLineParser(prog=prog, add_help=False, allow_abbrev=False)
        pre.add_argument(*cls.env_file_flags, dest="env_file", default=None)
        pre.add_argument("-h", "--help", action="store_true")
        early, _ = pre.parse_known_args(argv)
        env_file = cls._env_file_path(prog, early.env_file)
        if early.help:
            cls._build(prog, env_file, {}, ignore_missing=True)
            parser.print_help()
            raise SystemExit(0)
        parsed = vars(parser.parse_args(argv))
        blank = [(k, v) for k, v in parsed.items() if k in cls.model_fields and isinstance(v, str) and not v.strip()]
        if blank:  # pydantic-settings drops an empty flag as it drops an empty variable: it would be the default
            name, value = blank[0]
            error = {"loc": (name,), "msg": "empty; leave the flag out for its default", "type": "blank"}
            fail(prog, cls._describe([error], Path(DEFAULT_ENV_FILE), {name: value}, "command line", argv))
        own = {name: parsed[name] for name, field in cls.model_fields.items()
               if name in parsed and CLI_SUPPRESS in field.metadata}
        try:
            given = source(parsed_args={k: v for k, v in parsed.items() if k not in own})()
        except SettingsError as err:
            fail(prog, f"{err} (--help lists the options)")
        settings = cls._build(prog, env_file, {**given, **own}, argv=argv)
        settings._loaded()
        for line in unknown_variables(os.environ, dotenv_values(env_file) if env_file.is_file() else {}, cls):
            print(f"{prog}: warning: {line}", file=sys.stderr)
        return settings

    def _loaded(self) -> None:
        """Called once a process's settings are loaded (a model may say something about them first)."""

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
            where = f"{var}={os.environ[var]!r} (environment)" if names else f"{var} (environment)"
        elif var and env_file.is_file() and (dotenv_values(env_file).get(var) or ""):
            where = f"{var}={dotenv_values(env_file)[var]!r}" if names else var  # a variable-only one is a secret
            where += f" (.env file {env_file})"
        else:
            where = f"{names[0] if names else var or name} (default {field.default!r})"
        return f"bad setting {where}: {reason}{more}"

    @classmethod
    def given(cls: type[S], **values: Any) -> S:
        """Settings of ``values`` and the defaults only, nothing read from the environment or a .env file (tests,
        a process built inside another). A bad value raises pydantic's ValidationError."""
        token = _ONLY_GIVEN.set(True)
        try:
            return cls(**values)
        finally:
            _ONLY_GIVEN.reset(token)

    def variable(self, var: str) -> str | None:
        """The text of variable ``var`` as these settings read it: the environment, else their .env file (None: unset
        or empty there)."""
        env_file = self._env_file or Path(DEFAULT_ENV_FILE)
        return os.environ.get(var) or ((dotenv_values(env_file).get(var) if env_file.is_file() else None) or None)

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


def unknown_variables(environ: Mapping[str, str], env_file: Mapping[str, str | None],
                      model: type[Settings] | None = None) -> list[str]:
    """A line for each FEDRL_* variable (environment, then the .env file's) that neither ``model`` nor any process or
    deployment file of this project reads (runtime/variables.py), naming the closest one: a misspelt setting would
    otherwise be dropped without a word."""
    from runtime.variables import KNOWN  # generated: python -m deploy.reference --variables

    known = KNOWN | {var for name, field in (model.model_fields.items() if model else ())
                     if (var := env_name(name, field)) is not None}
    lines = []
    for where, names in (("environment", list(environ)), (".env file", list(env_file))):
        for var in sorted(v for v in names if v.startswith(ENV_PREFIX) and v not in known):
            close = difflib.get_close_matches(var, sorted(known), n=1, cutoff=0.6)
            hint = f"did you mean {close[0]}?" if close else "docs/settings.md lists every setting"
            lines.append(f"{var} ({where}) is no setting of any process, ignored ({hint})")
    return lines


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


def _add_argument(cls: type[Settings], parser: Any, *names: str, **kwargs: Any) -> Any:
    """pydantic-settings' add_argument, except that a ``CliSuppress`` field (help suppressed) gets no flag at all, and
    a field's help names the variable only where it reads one and shows its own ``metavar`` (see :func:`setting`)."""
    if kwargs.get("help") == argparse.SUPPRESS:
        return None
    field = cls.model_fields.get(kwargs.get("dest", ""))
    if field is not None:
        meta = _meta(field)
        if not meta["env"] and isinstance(kwargs.get("help"), str):
            kwargs["help"] = re.sub(r" \[env: [A-Z0-9_]+\]$", "", kwargs["help"])
        if meta["metavar"]:
            kwargs["metavar"] = meta["metavar"]
    return parser.add_argument(*names, **kwargs)


class _OneLineParser(argparse.ArgumentParser):
    """An option error is one line on stderr and exit code 2 (no usage dump)."""

    def error(self, message: str) -> NoReturn:
        fail(self.prog, f"{message} (--help lists the options)")


# -- settings every MQTT client shares -----------------------------------------------------------------------------


class LearnerTaskSettings(Settings):
    """A task and the learner that acts in it, with the QUBE tasks' action set, checked together here once: a
    learner that cannot act in the task's action space is refused in one line before a process starts. A process's
    settings inherit this and may give the three fields help text of their own."""

    env: TaskName = setting("CartPole-v0", "task to learn")
    qube_actions: QubeActions = qube_actions_setting()
    algo: LearnerName = setting(learners.DEFAULT, "learner (python -m worker.learners lists them)")

    @model_validator(mode="after")
    def _learner_fits(self) -> Self:
        fits_task(self.algo, self.env, self.qube_actions)
        return self


class MqttSettings(Settings):
    """Where the broker is, how to log in, and how loud to log."""

    broker: str = setting(DEFAULT_BROKER, "broker URL mqtt://[user:pass@]host:port, or mqtts:// for TLS "
                          "(memory://NAME: the in-memory hub NAME of this process, for services run in one process)")
    mqtt_username: str | None = setting(None, "broker user name (make-users.sh writes one per process)")
    mqtt_password: CliSuppress[str | None] = setting(None, "broker password (a variable only: flags show in the "
                                                     "process list)")
    mqtt_ca_file: Path | None = setting(None, "CA certificate of a TLS broker")
    max_payload: int | None = setting(None, "bytes; larger messages travel in chunks (e.g. 131072 for AWS IoT "
                                      "Core's 128 KB cap); 0 or unset: no chunking")
    log_level: LogLevel = setting("INFO", "DEBUG, INFO, WARNING or ERROR")

    @field_validator("broker")
    @classmethod
    def _broker_parses(cls, value: str) -> str:
        connector(value)  # a transport takes it (nothing connects yet)
        return value

    @field_validator("max_payload")
    @classmethod
    def _payload(cls, value: int | None) -> int | None:
        if value is not None and value != 0 and value < 1024:
            raise ValueError("must be at least 1024 bytes (or 0 for no chunking)")
        return value or None

    def _loaded(self) -> None:
        if "broker" not in self.model_fields_set:  # started by hand with no broker: say which one it joins, first
            print(f"{self._prog}: no broker configured (--broker, FEDRL_BROKER): joining {self.broker}",
                  file=sys.stderr, flush=True)

    def _login(self) -> dict[str, str | None]:
        return {"username": self.mqtt_username, "password": self.mqtt_password,
                "ca_file": str(self.mqtt_ca_file) if self.mqtt_ca_file else None}

    def address(self) -> BrokerAddress:
        """The MQTT broker with these credentials (explicit ones win over those in the URL)."""
        return BrokerAddress.parse(self.broker, **self._login())

    def where(self) -> str:
        """The broker as logs and summary.json name it: an MQTT broker without its login, another transport's address
        as it is."""
        return self.broker if transport_of(self.broker) else str(self.address())

    def connector(self) -> Connect:
        """How this process connects: protocol.transport.connector of its broker address (MQTT: with the login) and
        max_payload."""
        return connector(self.broker, self.max_payload, **self._login())


class RunMqttSettings(MqttSettings):
    """An MQTT client of one run (topic prefix fedrl/<run>/)."""

    run_id: str = setting("default", "run name, the topic prefix fedrl/<run>/")

    @field_validator("run_id")
    @classmethod
    def _run_id(cls, value: str) -> str:
        return check_id(value, "run id")


class RunKeySettings(Settings):
    """The run's key, shared by its chief and workers: the chief tags every message with it, the workers check."""

    run_key: CliSuppress[str | None] = setting(None, "the run's secret key (at least 16 characters; a variable "
                                               "only): the chief tags its messages with an HMAC under it and the "
                                               "workers refuse any without a valid tag; unset: workers trust any "
                                               "publisher on the run's topics")

    @field_validator("run_key")
    @classmethod
    def _key(cls, value: str | None) -> str | None:
        if value:
            key_bytes(value)
        return value or None

    def key(self) -> bytes | None:
        """The key as the HMAC takes it (None: no key)."""
        return key_bytes(self.run_key) if self.run_key else None
