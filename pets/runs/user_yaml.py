"""A YAML file a user gives (``--config``): read whole only up to a size no config reaches, and without YAML's
aliases, so that a file can neither hold the process (``/dev/zero``, a huge file) nor expand an alias chain into
more data than memory holds (a few hundred bytes of nested ``*alias`` lists)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

#: The largest config file read: a resolved config is about 3 KB; far above any real one.
MAX_BYTES = 1_000_000


class _NoAliases(yaml.SafeLoader):
    """yaml's safe loader that refuses an alias (``*name``): a config names each value once."""

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            raise yaml.YAMLError("aliases (*name) are not accepted in a config file; write each value out")
        return super().compose_node(parent, index)


def load_user_yaml(path: Path) -> Any:
    """The YAML document of ``path``; ValueError (its first line) for a file over :data:`MAX_BYTES`, not text or not
    YAML, or with an alias; OSError as reading raises it."""
    with open(path, "rb") as f:
        data = f.read(MAX_BYTES + 1)
    if len(data) > MAX_BYTES:
        raise ValueError(f"over {MAX_BYTES:,} bytes; a config file is a few KB")
    try:
        return yaml.load(data.decode(), Loader=_NoAliases)  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as err:
        raise ValueError(str(err).splitlines()[0]) from None
