"""Robot files are untrusted input: what they say is read as data, never as a way to reach
other files or the network.

- **XML** is parsed by expat with every DTD refused: no entity can be declared, so no
  entity-expansion bomb ("billion laughs") and no external entity (a file or a URL pulled
  into the text) gets through (`parse_xml`).
- **Files a model names** (meshes, textures, included files) resolve only inside the model's
  folder, or for `package://NAME/...` inside the folder the caller gives as `package_map[NAME]`;
  absolute paths, URIs (`file://`, `http://`, ...) and paths that leave the folder, through
  `..` or a symbolic link, are refused before anything is opened (`resolve_model_file`).

Each refusal is raised as the reader's own error class (`URDFError`, `MJCFError`), naming
the file, the element and the remedy.
"""

from __future__ import annotations

import pathlib
import re
import xml.etree.ElementTree as ET
from xml.parsers import expat

_SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*:")  # file:, http:, package:, C: ...


class _Refused(Exception):
    """Raised inside expat's handlers: the document declares a DTD or an entity."""


def parse_xml(data: bytes, source, error: type[Exception]) -> ET.Element:
    """The root element of the XML document `data` (bytes, in the encoding it declares),
    parsed without a DTD: a `<!DOCTYPE>` or `<!ENTITY>` is refused with `error` naming
    `source`, as is text that is not well-formed XML. Namespaced names read as
    `xml.etree`'s (`{uri}name`)."""
    builder = ET.TreeBuilder()
    parser = expat.ParserCreate(namespace_separator="}")

    def refuse(*_):
        raise _Refused

    parser.StartDoctypeDeclHandler = refuse
    parser.EntityDeclHandler = refuse
    parser.UnparsedEntityDeclHandler = refuse
    parser.ExternalEntityRefHandler = refuse
    parser.SetParamEntityParsing(expat.XML_PARAM_ENTITY_PARSING_NEVER)
    name = lambda n: "{" + n if "}" in n else n  # noqa: E731  expat's 'uri}local' as '{uri}local'
    parser.StartElementHandler = lambda tag, attributes: builder.start(
        name(tag), {name(k): v for k, v in attributes.items()})
    parser.EndElementHandler = lambda tag: builder.end(name(tag))
    parser.CharacterDataHandler = builder.data
    parser.buffer_text = True
    try:
        parser.Parse(data, True)
    except _Refused:
        raise error(f"{source}: XML DOCTYPE / ENTITY declarations are not accepted in a robot file (they "
                    "allow entity-expansion bombs and external entities that read files or the network); "
                    "remove the DOCTYPE and write the values out") from None
    except expat.ExpatError as e:
        raise error(f"{source}: not well-formed XML: {e}") from None
    return builder.close()


def local_tag(tag: str) -> str:
    """A tag's name without its namespace ('{http://drake.mit.edu}capsule' -> 'drake:capsule')."""
    if tag.startswith("{"):
        uri, _, name = tag[1:].partition("}")
        return f"drake:{name}" if "drake" in uri else name
    return tag


def children_named(element, name):
    """The children of `element` whose `local_tag` is `name`."""
    return [c for c in element if local_tag(c.tag) == name]


def read_xml(path, error: type[Exception]) -> ET.Element:
    """`parse_xml` of the file at `path` (an unreadable file refused with `error`)."""
    path = pathlib.Path(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise error(f"cannot read {path}: {e}") from None
    return parse_xml(data, path, error)


def resolve_model_file(filename, model, where: str, error: type[Exception], *, package_map=None, base=None,
                       must_exist: bool = True) -> pathlib.Path:
    """The file that `filename` (as written in the robot file `model`) names, resolved.

    A relative path is taken from `base` (default: the model's folder; e.g. MuJoCo's
    `meshdir` inside it), `package://NAME/rest` from `package_map[NAME]` (`package_map` None:
    the format has no packages, as MJCF); the result, every
    symbolic link followed, must lie inside the model's folder (or that package folder).
    Absolute paths, other URIs and escapes are refused with `error` naming `model`, `where`
    (the element), the filename and the remedy; so is a missing file when `must_exist`."""
    model = pathlib.Path(model)
    root, folder = model.resolve().parent, "the model's folder"
    text = str(filename or "")
    or_package = "" if package_map is None else ", or pass its package's folder as package_map="
    if not text:
        raise error(f"{model}: {where}: no filename given")
    if text.startswith("package://") and package_map is not None:
        package, _, relative = text[len("package://"):].partition("/")
        if package not in package_map:
            raise error(f"{model}: {where}: {text!r} names package {package!r}; pass "
                        f"package_map={{{package!r}: '/path/to/{package}'}} to say which folder it is "
                        "(package folders are never searched for)")
        root = start = pathlib.Path(package_map[package]).resolve()
        folder = f"the folder of package {package!r}"
    elif _SCHEME.match(text) or pathlib.PurePosixPath(text).is_absolute() or pathlib.PureWindowsPath(text).is_absolute():
        raise error(f"{model}: {where}: {text!r} is not a path relative to the model's folder (absolute "
                    "paths and URIs such as file:// or http:// are not read); move the file into the "
                    f"folder {root} and name it relative to it{or_package}")
    else:
        relative, start = text, root if base is None else pathlib.Path(base)
    target = (start / relative).resolve()
    if target != root and root not in target.parents:
        raise error(f"{model}: {where}: {text!r} resolves to {target}, outside {folder} {root}; only files "
                    f"inside it are read: move the file into the folder (a symbolic link out of it does not "
                    f"count){or_package}")
    if must_exist and not target.is_file():
        raise error(f"{model}: {where}: {text!r}: the file {target} does not exist")
    return target
