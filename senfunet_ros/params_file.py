"""ROS 2 parameter files without a node: which sections reach a node (as rcl matches them), and
the node's checked settings from a file, for `senfunet replay`, `senfunet node --params` and the
node's own check of the `--params-file` arguments it was started with."""
from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from senfunet_ros import params as P

__all__ = ["load_settings", "node_section_applies", "read_params_file", "shared_parameter_names"]


def _flatten(tree: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(_flatten(value, name + "."))
        else:
            out[name] = value
    return out


def _node_sections(tree: dict[Any, Any], prefix: str = "") -> list[tuple[str, dict[str, Any]]]:
    """(node name, its ros__parameters) of each section, in file order; nested keys name the
    namespaces (`robot1: senfunet: ros__parameters:` is robot1/senfunet, `/**: senfunet: ...` is
    /**/senfunet), as rcl reads them."""
    out: list[tuple[str, dict[str, Any]]] = []
    for key, value in tree.items():
        if not isinstance(value, dict):
            continue
        name = f"{prefix}/{str(key).lstrip('/')}" if prefix else str(key)
        if isinstance(value.get("ros__parameters"), dict):
            out.append((name, value["ros__parameters"]))
        elif "ros__parameters" not in value:
            out += _node_sections(value, name)
    return out


def _check_lists(path: Path, parameters: dict[str, Any]) -> None:
    """ValueError for a list that mixes types, which rcl refuses for the whole file (the node would not
    start): integers among decimals, above all (an extrinsic written [0.1, 0, 0, ...])."""
    for name, value in _flatten(parameters).items():
        if not isinstance(value, list) or not value:
            continue
        kinds = {type(item).__name__ for item in value}
        if len(kinds) > 1:
            advice = ("write every number with a decimal point, e.g. [0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]"
                      if kinds <= {"int", "float"} else "make its items one type")
            raise ValueError(f"{path}: parameter {name} = {value} mixes {' and '.join(sorted(kinds))} items, which "
                             f"ROS's parameter file parser refuses (the node would not start); {advice}")


def node_section_applies(key: str, node_fqn: str) -> bool:
    """Whether a parameter file's section `key` reaches the node `node_fqn` ("/robot1/senfunet") as rcl
    matches them: a key without a leading '/' is absolute ("senfunet" is "/senfunet", which a node in
    a namespace does not get), '*' stands for one name and '/**' for any number of namespaces."""
    pattern = re.escape(key if key.startswith("/") else "/" + key)
    return re.fullmatch(pattern.replace(r"/\*\*", "(/[^/]+)*").replace(r"\*", "[^/]*"), node_fqn) is not None


def _sections(path: Path) -> tuple[list[dict[Any, Any]], list[tuple[str, dict[str, Any]]]]:
    """A parameter file's YAML documents and its node sections (`_node_sections`), in file order;
    ValueError for what rcl would refuse or cannot read."""
    import yaml

    from senfunet_core.files import yaml_error_text

    try:
        text = path.read_text()
        if any(isinstance(event, yaml.AliasEvent) for event in yaml.parse(text)):
            raise ValueError(f"{path}: uses a YAML alias (*name), which ROS's parameter file parser refuses (the "
                             "node would not start); write the values out")
        docs = [doc for doc in yaml.safe_load_all(text) if doc is not None]
    except OSError as err:
        raise ValueError(f"{path}: cannot read the parameter file: {err.strerror}") from None
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a text file; pass a YAML parameter file such as config/default.yaml") from None
    except yaml.YAMLError as err:
        raise ValueError(f"{path}: {yaml_error_text(err)}") from None
    if not docs or not all(isinstance(doc, dict) for doc in docs):
        raise ValueError(f"{path}: expected '{P.NODE_NAME}: ros__parameters: ...' at the top")
    sections = [section for doc in docs for section in _node_sections(doc)]  # rcl reads every document in turn
    for _, parameters in sections:
        _check_lists(path, parameters)
    return docs, sections


def shared_parameter_names(path: Path, node_fqn: str = f"/{P.NODE_NAME}") -> set[str]:
    """The names the node gets from a file's sections for every node ('/**', '/*') alone: there, a name
    the node does not have may be another node's (robot_name), not a typo."""
    _, sections = _sections(path)
    applies = [(key, _flatten(parameters)) for key, parameters in sections if node_section_applies(key, node_fqn)]
    named = {name for key, values in applies if not key.rstrip("/").endswith("*") for name in values}
    return {name for key, values in applies if key.rstrip("/").endswith("*") for name in values} - named


def read_params_file(path: Path, *, node_sections_only: bool = False, node_fqn: str = f"/{P.NODE_NAME}"
                      ) -> dict[str, Any]:
    """The `ros__parameters` of a ROS 2 parameter file, flattened: those of every section that reaches the
    node `node_fqn` (later ones override earlier ones, as in rcl), else its only section unless
    `node_sections_only` (ROS gives the node only its own)."""
    docs, sections = _sections(path)
    nodes = dict(sections)
    ours = [parameters for key, parameters in sections if node_section_applies(key, node_fqn)]
    if ours:
        return {name: value for parameters in ours for name, value in _flatten(parameters).items()}
    if len(nodes) == 1 and not node_sections_only:
        return _flatten(next(iter(nodes.values())))
    name = node_fqn.rsplit("/", 1)[-1]
    if node_fqn != f"/{name}" and any(node_section_applies(key, f"/{name}") for key in nodes):
        # the usual file (config/default.yaml) with the node started in a namespace: rcl would give it none
        raise ValueError(f"{path}: its section for '{name}' is for the node without a namespace; the node "
                         f"{node_fqn} would ignore it and run with the defaults: name the section "
                         f"'/**/{name}' (any namespace) or '{node_fqn}'")
    near = [f"'{key}' holds {sorted(map(str, value))}" if isinstance(value, dict) else f"'{key}' is empty"
            for doc in docs for key, value in doc.items()
            if node_section_applies(str(key), node_fqn) and not (isinstance(value, dict) and
                                                                  isinstance(value.get("ros__parameters"), dict))]
    if near:  # a section for the node, but no parameters in it: ros_parameters, a missing level, nothing under it
        raise ValueError(f"{path}: its section for the node has no parameters under 'ros__parameters:' "
                         f"({'; '.join(near)}); write '{name}:', then 'ros__parameters:' indented under it, then "
                         "the parameters indented under that")
    if nodes and not node_sections_only:  # replay: no node to name, and no way to choose among the sections
        raise ValueError(f"{path}: no '{name}: ros__parameters:' section, and several for other nodes "
                         f"({sorted(nodes)}): replay reads the section for '{name}' (or '/**'), or a file's only "
                         "section; copy the one to use into a file of its own")
    raise ValueError(f"{path}: no '{name}: ros__parameters:' section" + (
        f" (its sections {sorted(nodes)} are for other nodes: the node, named '{node_fqn}', would ignore them)"
        if nodes else ""))


def load_settings(params_file: str | Path | None = None, overrides: dict[str, Any] | None = None, *,
                  node_sections_only: bool = False, node_fqn: str = f"/{P.NODE_NAME}") -> P.Settings:
    """The node's parameters from a parameter file (or the defaults), checked like the node does.

    Unknown names are refused (a typo would otherwise be ignored silently), but for those that only a
    section for every node ('/**') gives and that are no near miss of ours: another node's (robot_name),
    which the node ignores; and with
    `node_sections_only` a file without a section for the node `node_fqn` (its namespace and name,
    as remapped). ValueError on bad values.
    """
    given: dict[str, Any] = {}
    shared: set[str] = set()  # names from sections for every node: another node's there is no typo of ours
    if params_file is not None:
        given.update(read_params_file(Path(params_file), node_sections_only=node_sections_only, node_fqn=node_fqn))
        shared = shared_parameter_names(Path(params_file), node_fqn) - set(overrides or {})
    given.update(overrides or {})
    sensors = [str(s) for s in given.get("sensors", P.GLOBAL_PARAMS[0].default)]
    table = P.expanded_defaults(sensors)
    unknown = P.unknown_parameters({name for name in given if name not in shared}, sensors) + [
        name for name in P.unknown_parameters(shared, sensors) if "(did you mean" in name]  # a typo of ours
    if unknown:
        where = f" in {params_file}" if params_file else ""
        raise ValueError(f"unknown parameter(s){where}: {', '.join(unknown)}; see config/default.yaml for the names")
    given = {name: value for name, value in given.items() if name in table}
    values = {name: P.coerce(name, given.get(name, default), default) for name, (default, _) in table.items()}
    P.check(values)
    return P.Settings.from_values(values)
