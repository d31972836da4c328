"""Reading one YAML document from untrusted bytes: UTF-8 text, nesting and alias expansion bounded, any failure one
`UnusableYaml` error saying where. A car config holds a few hundred values; PyYAML would otherwise build a
billion-laugh alias bomb in microseconds (aliases are shared references) and hand it to a validator that walks it for
hours, compose a few MiB of plain values for tens of seconds, overflow the stack on deep nesting, or raise plain
ValueError on a 5,000-digit integer."""

from __future__ import annotations

import yaml

MAX_BYTES = 4 * 1024 * 1024  # far above any config, far below trouble
MAX_EXPANDED_NODES = 200_000  # values the document holds once every alias is expanded


class UnusableYaml(ValueError):
    """The bytes are not a YAML document we will read (the message says why, and where)."""


def _children(node: yaml.Node) -> list[yaml.Node]:
    if isinstance(node, yaml.SequenceNode):
        return list(node.value)
    if isinstance(node, yaml.MappingNode):
        return [n for pair in node.value for n in pair]
    return []


def _check_expansion(root: yaml.Node) -> None:
    """Refuse a node graph that expands to more than MAX_EXPANDED_NODES values or refers to itself (an alias
    inside its own anchor); linear in the distinct nodes, whatever they expand to."""
    expanded: dict[int, int] = {}
    on_path: set[int] = set()
    stack: list[tuple[yaml.Node, bool]] = [(root, False)]
    while stack:
        node, finished = stack.pop()
        key = id(node)
        if finished:
            on_path.discard(key)
            expanded[key] = 1 + sum(expanded[id(c)] for c in _children(node))
            if expanded[key] > MAX_EXPANDED_NODES:
                raise UnusableYaml(f"expands to more than {MAX_EXPANDED_NODES} values through its aliases "
                                   f"(line {node.start_mark.line + 1}): not a car config")
            continue
        if key in expanded:
            continue
        on_path.add(key)
        stack.append((node, True))
        for child in _children(node):
            if id(child) in on_path:
                raise UnusableYaml(f"an alias refers to its own anchor (line {child.start_mark.line + 1})")
            if id(child) not in expanded:
                stack.append((child, False))


class _BoundedLoader(yaml.SafeLoader):
    """SafeLoader that stops composing past MAX_EXPANDED_NODES values (each alias counts one): a plain document of
    a few MiB of values took PyYAML tens of seconds to compose before the expansion check refused it."""

    def __init__(self, text: str) -> None:
        super().__init__(text)
        self.composed = 0

    def compose_node(self, parent, index):
        self.composed += 1
        if self.composed > MAX_EXPANDED_NODES:
            line = self.peek_event().start_mark.line + 1
            raise UnusableYaml(f"holds more than {MAX_EXPANDED_NODES} values (line {line}): not a car config")
        return super().compose_node(parent, index)


def _where(exc: yaml.YAMLError) -> str:
    """PyYAML's error on one line: where (line and column from 1, or the character's position) and what; its own
    message spans several (the document's name, an excerpt, a caret)."""
    if isinstance(exc, yaml.MarkedYAMLError) and exc.problem_mark is not None:
        mark = exc.problem_mark
        text = f"line {mark.line + 1}, column {mark.column + 1}: {exc.problem or exc.context}"
        if exc.problem and exc.context:
            since = exc.context_mark
            text += f" ({exc.context}" + (f" from line {since.line + 1}, column {since.column + 1})" if since else ")")
        return text
    if isinstance(exc, yaml.reader.ReaderError) and isinstance(exc.character, int):
        return f"position {exc.position}: unacceptable character #x{exc.character:04x}: {exc.reason}"
    return " ".join(str(exc).split())


def load_yaml(data: bytes) -> object:
    """The document in `data` (None when it is empty); UnusableYaml for anything we will not read."""
    if len(data) > MAX_BYTES:
        raise UnusableYaml(f"{len(data)} bytes: far too large for a car config")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise UnusableYaml(f"not UTF-8 text (byte {exc.start}: 0x{data[exc.start]:02x})") from None
    loader = None
    try:
        loader = _BoundedLoader(text)  # its reader refuses control characters at once
        node = loader.get_single_node()
        if node is None:
            return None
        _check_expansion(node)
        return loader.construct_document(node)
    except UnusableYaml:
        raise
    except yaml.YAMLError as exc:
        raise UnusableYaml(f"not valid YAML: {_where(exc)}") from None
    except RecursionError:
        raise UnusableYaml("nested too deeply") from None
    except ValueError as exc:  # PyYAML's constructors: an integer of too many digits, a bad timestamp, ...
        raise UnusableYaml(f"unreadable value: {exc}") from None
    finally:
        if loader is not None:
            loader.dispose()
