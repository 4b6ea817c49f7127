"""Config text read and written: ``--set KEY=VALUE``, ``--config`` files, saved configs, ``--list-keys``.

Every value goes in as the text ``--set`` takes (a file's or a saved config's values are written out so),
is parsed by its key's declaration (``config.key_specs``) and checked by ``config.validate``; an old key
name is read under its new one (``config_history``).  ``--config`` files and saved ``config.json`` files
are read within bounds (``MAX_CONFIG_BYTES``, ``MAX_CONFIG_DEPTH``, ``MAX_NUMBER_DIGITS``; YAML only as
JSON's types), which ``parse_json`` / ``parse_yaml`` hold for every config-like text of the package.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import textwrap
from typing import Any

from sagrasp_jax.task.config import (
    PRESETS, Config, ConfigError, KeySpec, flatten_keys, format_number, get_config, get_key, key_specs,
    robot_defaults, valid_keys, validate,
)
from sagrasp_jax.task import robots
from sagrasp_jax.task.config_history import RENAMED_KEYS, current_name, upgrade_flat


def _scalar(text: str, kind: type) -> Any:
    text = text.strip()
    if kind is bool:
        if text.lower() not in ("true", "1", "yes", "false", "0", "no"):
            raise ValueError("expected true/false")
        return text.lower() in ("true", "1", "yes")
    if kind is int:
        number = float(text) if any(c in text for c in ".eE") else int(text)
        if not float(number).is_integer():
            raise ValueError("expected an integer")
        return int(number)
    return float(text) if kind is float else text


def _parse(text: str, spec: KeySpec, name: str) -> Any:
    """A value written as text (``--set``; files and saved configs are written so too): ``true``/``false``,
    numbers, ``none`` for an unset optional key, a list as ``a,b,c`` or JSON."""
    text = text.strip()
    if spec.optional and text.lower() in ("none", "null"):
        return None
    try:
        if not spec.listed:
            return _scalar(text, spec.kind)
        items = json.loads(text) if text.startswith("[") else [t for t in text.split(",") if t.strip()]
        value = tuple(_scalar(v if isinstance(v, str) else json.dumps(v), spec.kind) for v in items)
        if spec.length not in (None, len(value)):
            raise ValueError(f"expected {spec.length} values, got {len(value)}")
        return value
    except (ValueError, OverflowError, TypeError) as exc:
        raise ConfigError(f"bad value {text!r} for {name} ({spec.type_name}): {exc}") from None


def unknown_key_message(name: str) -> str:
    """An unknown key names the nearest valid keys (difflib), not all of them."""
    keys = valid_keys()
    leaf = name.rsplit(".", 1)[-1]
    near = difflib.get_close_matches(name, keys, n=4, cutoff=0.6)
    near += [k for k in keys if k not in near and difflib.SequenceMatcher(None, leaf, k.rsplit(".", 1)[-1]).ratio() >= 0.8]
    hint = f"; did you mean {', '.join(near[:5])}?" if near else ""
    return f"unknown config key {name!r}{hint} (--list-keys lists every key)"


def _replaced(section: Any, path: list[str], value: Any) -> Any:
    inner = value if len(path) == 1 else _replaced(getattr(section, path[0]), path[1:], value)
    return dataclasses.replace(section, **{path[0]: inner})


SHORT_KEYS = {"robot": "env.robot"}  # ``--set robot=panda``: the one key short enough to deserve a short name


def apply_overrides(cfg: Config, overrides: list[str]) -> Config:
    """Apply ``key=value`` strings, e.g. ``ppo.num_envs=512``; validates the result.  Setting ``env.robot`` also
    sets the per-joint keys (``config.ROBOT_KEYS``) to that robot's values, except those set in the same list."""
    given = set()
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"override {item!r} is not of the form key=value")
        name, text = item.split("=", 1)
        name = SHORT_KEYS.get(name.strip(), current_name(name.strip()))
        if name not in key_specs():
            section = any(k.startswith(name + ".") for k in key_specs())
            raise ConfigError(f"{name!r} is a section, not a value; set one of its keys" if section
                              else unknown_key_message(name))
        cfg = _replaced(cfg, name.split("."), _parse(text, key_specs()[name], name))
        given.add(name)
    if "env.robot" in given and cfg.env.robot in robots.names():  # an unknown one: validate names the choices
        for name, value in robot_defaults(cfg.env.robot).items():
            if name not in given:
                cfg = _replaced(cfg, name.split("."), value)
    validate(cfg)
    return cfg


def _as_overrides(flat: dict[str, Any], where: str) -> list[str]:
    """A file's or saved config's values as the ``--set`` texts that mean them (so all are checked alike)."""
    out = []
    for name, value in flat.items():
        spec = key_specs().get(RENAMED_KEYS.get(name, name))
        if value is None and not (spec and spec.optional):
            raise ConfigError(f"{where}: {name} has no value (null)")
        out.append(f"{name}={value if isinstance(value, str) else json.dumps(value)}")
    return out


# A --config file and a saved config.json are read within these bounds (refused, ConfigError / RunDirError,
# beyond them): a config is a few kB with keys three sections deep.
MAX_CONFIG_BYTES = 256 << 10  # 256 KiB, 50 full configs; checked before the file is read (pure-Python YAML
# takes a few seconds for this much)
MAX_CONFIG_DEPTH = 32  # nested mappings and lists
MAX_NUMBER_DIGITS = 64  # digits of an integer, in any notation (Python's own int() stops at 4,300 with a ValueError)
_JSON_TYPES = (str, int, float, bool, type(None))


def check_int_literal(text: str) -> None:
    """Refuse (ValueError) an integer literal of more than ``MAX_NUMBER_DIGITS`` digits before it is converted,
    in every notation a config file may use: decimal, and YAML's hex ``0x``, octal ``0…``, binary ``0b``
    and base-60 ``1:20``, with a sign and ``_`` separators (neither counts).  Hex digits count like decimal ones:
    a bound on the characters, not the value (``check_int_value`` bounds that)."""
    body = text.strip().lstrip("+-").replace("_", "")
    if body[:2].lower() in ("0x", "0o", "0b"):
        body = body[2:]
    digits = sum(c.isalnum() for c in body)
    if digits > MAX_NUMBER_DIGITS:
        raise ValueError(f"an integer of {digits} digits (at most {MAX_NUMBER_DIGITS})")


def check_int_value(value: int) -> int:
    """``value`` if it has at most ``MAX_NUMBER_DIGITS`` decimal digits (a 64-digit hex literal has 78), else
    ValueError: every integer a config file yields can be written out and read back as ``--set`` text."""
    if abs(value) >= 10**MAX_NUMBER_DIGITS:
        raise ValueError(f"an integer of {len(str(abs(value)))} digits (at most {MAX_NUMBER_DIGITS})")
    return value


def _bounded_int(text: str) -> int:
    check_int_literal(text)
    return check_int_value(int(text))


def _check_plain(data: Any) -> None:
    """Refuse (ValueError) nesting deeper than ``MAX_CONFIG_DEPTH`` and any value that is not a JSON
    type (YAML's sets, dates, binary); iterative, so depth costs no recursion."""
    stack = [(data, 1)]
    while stack:
        node, depth = stack.pop()
        if depth > MAX_CONFIG_DEPTH:
            raise ValueError(f"nested deeper than {MAX_CONFIG_DEPTH} levels")
        if isinstance(node, dict):
            for k, v in node.items():
                if not isinstance(k, _JSON_TYPES):
                    raise ValueError(f"a key of type {type(k).__name__} ({k!r}); keys are strings")
                stack.append((v, depth + 1))
        elif isinstance(node, list):
            stack.extend((v, depth + 1) for v in node)
        elif not isinstance(node, _JSON_TYPES):
            raise ValueError(f"a value of type {type(node).__name__} ({str(node)[:60]!r}); a config holds mappings, "
                             "lists, strings, numbers, booleans and null only")


def parse_json(text: str | bytes) -> Any:
    """JSON within the config bounds: integers of at most ``MAX_NUMBER_DIGITS`` digits, nesting of at
    most ``MAX_CONFIG_DEPTH``; ValueError (``json.JSONDecodeError`` among them) otherwise."""
    try:
        data = json.loads(text, parse_int=_bounded_int)
    except RecursionError:
        raise ValueError(f"nested deeper than {MAX_CONFIG_DEPTH} levels") from None
    _check_plain(data)
    return data


def _yaml_loader() -> type:
    """PyYAML's SafeLoader, narrowed to JSON's types: no aliases (so no billion-laughs expansion), no
    timestamps (``2001-12-14`` stays a string, which the key's type then refuses), no ``!!set``,
    ``!!binary``, ``!!omap`` or ``!!pairs``, and integers bounded like ``parse_json``'s."""
    import yaml

    class ConfigLoader(yaml.SafeLoader):
        def compose_node(self, parent: Any, index: Any) -> Any:
            if self.check_event(yaml.AliasEvent):
                event = self.peek_event()
                raise yaml.composer.ComposerError(None, None, f"an alias (*{event.anchor}) is not allowed in a config "
                                                  "file: write the value out", event.start_mark)
            return super().compose_node(parent, index)

        def fetch_flow_collection_start(self, token_class: Any) -> None:
            if self.flow_level >= MAX_CONFIG_DEPTH:  # refused while scanning: its simple-key table grows as depth²
                raise yaml.scanner.ScannerError(None, None, f"nested deeper than {MAX_CONFIG_DEPTH} levels",
                                                self.get_mark())
            super().fetch_flow_collection_start(token_class)

        def construct_yaml_int(self, node: Any) -> int:
            try:  # the literal's digits before PyYAML converts it (a hex one's letters count), then the value's
                check_int_literal(str(node.value))
                return check_int_value(super().construct_yaml_int(node))
            except (ValueError, IndexError) as exc:  # IndexError: PyYAML's on an empty !!int "" or "-"
                message = str(exc) if isinstance(exc, ValueError) else f"{str(node.value)[:40]!r} is not an integer"
                raise yaml.constructor.ConstructorError(None, None, message, node.start_mark) from None

        def refuse_tag(self, node: Any) -> Any:
            raise yaml.constructor.ConstructorError(None, None, f"tag {node.tag} is not allowed in a config file "
                                                    "(mappings, lists, strings, numbers, booleans and null only)",
                                                    node.start_mark)

    timestamp = "tag:yaml.org,2002:timestamp"
    ConfigLoader.yaml_implicit_resolvers = {
        first: [(tag, regexp) for tag, regexp in resolvers if tag != timestamp]
        for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()}
    ConfigLoader.add_constructor("tag:yaml.org,2002:int", ConfigLoader.construct_yaml_int)
    for tag in ("timestamp", "set", "binary", "omap", "pairs"):
        ConfigLoader.add_constructor(f"tag:yaml.org,2002:{tag}", ConfigLoader.refuse_tag)
    return ConfigLoader


def parse_yaml(text: str) -> Any:
    """YAML through ``_yaml_loader`` within the config bounds; ValueError or ``yaml.YAMLError`` otherwise."""
    import yaml

    try:
        data = yaml.load(text, Loader=_yaml_loader())  # noqa: S506 (a SafeLoader subclass)
    except RecursionError:
        raise ValueError(f"nested deeper than {MAX_CONFIG_DEPTH} levels") from None
    _check_plain(data)
    return data


def file_overrides(path: str) -> list[str]:
    """``--config FILE``: the file's keys as ``key=value`` overrides, applied over the chosen preset
    like ``--set`` (keys it leaves out keep the preset's values).  JSON; YAML (``.yaml``/``.yml``)
    when PyYAML is installed.  Sections may nest (``{"ppo": {"num_envs": 512}}``) or be dotted
    (``{"ppo.num_envs": 512}``).  A file that cannot be read or parsed raises ConfigError: it must be
    a regular file (not a FIFO or device: refused before it is opened) of at most ``MAX_CONFIG_BYTES``,
    nested at most ``MAX_CONFIG_DEPTH`` deep, with integers of at most ``MAX_NUMBER_DIGITS`` digits in any
    notation (hex, octal, binary, base 60), and YAML yields JSON's types only (no aliases, dates or sets)."""
    from sagrasp_jax.base import fileio

    where = f"--config {path}"
    if not path.lower().endswith((".json", ".yaml", ".yml")):
        raise ConfigError(f"{where}: expected a .json, .yaml or .yml file")
    try:
        text = fileio.read_regular(path, MAX_CONFIG_BYTES, "config file").decode("utf-8")
    except (fileio.NotRegularFile, fileio.FileTooLarge) as exc:  # their messages start with the path
        raise ConfigError(f"--config {exc}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{where}: cannot read it ({exc})") from None
    if path.lower().endswith(".json"):
        load, kind, errors = parse_json, "JSON", ()
    else:
        try:
            import yaml
        except ImportError:
            raise ConfigError(f"{where}: reading YAML needs PyYAML (pip install pyyaml), or use JSON") from None
        load, kind, errors = parse_yaml, "YAML", (yaml.YAMLError,)
    try:
        data = load(text)
    except (ValueError, *errors) as exc:
        raise ConfigError(f"{where}: not valid {kind} ({exc})") from None
    return _as_overrides(flatten_keys(data, "", where), where)


def config_from_dict(data: dict[str, Any]) -> Config:
    """Build and validate a Config from its dict (``config.config_to_dict``'s), read like ``--set`` over the
    defaults; an older layout is upgraded first (``config_history.upgrade_flat``: keys it lacks get their
    legacy value)."""
    if not isinstance(data, dict):
        raise ConfigError(f"saved config must be a JSON object, got {type(data).__name__}")
    return apply_overrides(Config(), _as_overrides(upgrade_flat(flatten_keys(data, "", "saved config")), "saved config"))


def _shown(value: Any) -> str:
    if isinstance(value, tuple):
        return ",".join(_shown(v) for v in value)
    if isinstance(value, bool) or value is None:
        return str(value).lower()
    return format_number(value) if isinstance(value, (int, float)) else str(value)


def describe_keys(preset: str = "cpu-quick") -> str:
    """``--list-keys``: every key with its type, its value in ``preset``, its valid values (range or
    choices), the other presets' values where they differ, and its description."""
    cfg = get_config(preset)
    others = {name: get_config(name) for name in PRESETS if name != preset}
    lines = [f"config keys (values of preset {preset!r}; set with --set KEY=VALUE, a list as a,b,c):", ""]
    for name, spec in key_specs().items():
        value, each = get_key(cfg, name), "each " * spec.listed
        valid = (f"; {each}in {spec.range}" if spec.range else "") + \
            (f"; {each}one of {', '.join(map(str, spec.choices))}" if spec.choices else "")
        differ = [f"{other} {_shown(get_key(c, name))}" for other, c in others.items() if get_key(c, name) != value]
        lines.append(f"{name} = {_shown(value)}  ({spec.type_name}{valid})" + (f"  [{'; '.join(differ)}]" if differ else ""))
        lines += textwrap.wrap(spec.doc, 100, initial_indent="    ", subsequent_indent="    ") or ["    (no description)"]
    return "\n".join(lines)
