"""OPC UA controllers (``opc.tcp://HOST:PORT/…``), through ``asyncua`` (the ``link`` extra).

Variables are node ids in their string form (``ns=2;s=Robot.Stroke1``, ``ns=3;i=1042``). A poll is
one Read service call of the stamp, every ``[read]`` node and the stamp again; the estimate goes
back in one Write call, each value in the variant type the node holds (read at the start: a
Double array, an Int32 counter).

The client runs on an event loop of its own, driven in the caller's thread: a read or a write runs
the loop until its answer, and :meth:`OpcUaConnection.wait` runs it while the caller waits, so the
client's keep-alive and channel renewal go on between polls.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Sequence
from typing import Any

from ..errors import CalibError, shown
from . import ARRAY_KEYS, LinkDown, WriteFailed

try:
    from asyncua import Client, ua
except ImportError:  # the optional extra: said when a link is used, not at import
    Client = ua = None  # type: ignore[assignment,misc]

#: what goes wrong with a connection (as opposed to a refused value): retried as a lost link.
_DOWN = (OSError, asyncio.TimeoutError, ConnectionError, EOFError)


def connect(url: str, timeout_s: float) -> OpcUaConnection:
    if Client is None:
        raise CalibError("link: an OPC UA link needs the asyncua package (pip install 'stewart-calib[link]')")
    return OpcUaConnection(url, timeout_s)


def _numeric_types() -> set:
    """The variant types a sample's value, a counter or a written number may have."""
    V = ua.VariantType
    return {
        V.Boolean, V.SByte, V.Byte, V.Int16, V.UInt16, V.Int32, V.UInt32, V.Int64, V.UInt64, V.Float, V.Double
    }  # fmt: skip


class OpcUaConnection:
    """One session with an OPC UA server (see the module docstring)."""

    def __init__(self, url: str, timeout_s: float):
        # asyncua logs every lost connection as a traceback: the link says it in one line itself
        logging.getLogger("asyncua").setLevel(logging.CRITICAL + 1)
        self.url = url
        self._loop = asyncio.new_event_loop()
        self._client = Client(url, timeout=timeout_s)
        self._nodes: list[Any] = []
        self._writes: list[tuple[str, Any, Any]] = []  # key, node id, variant type
        try:
            self._run(self._client.connect())
        except BaseException:
            self._loop.close()
            raise

    def _run(self, coroutine):
        try:
            return self._loop.run_until_complete(coroutine)
        except _DOWN as err:
            raise LinkDown(_words(err)) from None
        except ua.UaStatusCodeError as err:
            if _connection_status(err):
                raise LinkDown(_words(err)) from None
            raise

    def check(self, reads: dict[str, str], stamp: str, writes: dict[str, str], lengths: dict[str, int]) -> None:
        numeric = _numeric_types()
        labelled = [("link.sample" if stamp not in reads.values() else _label(reads, stamp), stamp)]
        labelled += [(f"read.{column}", name) for column, name in reads.items()]
        labelled += [(f"write.{key}", name) for key, name in writes.items()]
        ids = [_node_id(label, name) for label, name in labelled]
        values = self._run(self._client.uaclient.read_attributes(ids, ua.AttributeIds.Value))
        kinds = self._run(self._client.uaclient.read_attributes(ids, ua.AttributeIds.DataType))
        for (label, name), value, kind in zip(labelled, values, kinds, strict=True):
            if not value.StatusCode.is_good():
                raise CalibError(
                    f"{label} = '{shown(name)}': not on the controller ({value.StatusCode.name}); "
                    "expected a variable it publishes"
                )
            variant = value.Value
            vtype = variant.VariantType if variant is not None else None
            if vtype in (None, ua.VariantType.Null) and kind.StatusCode.is_good():
                vtype = _variant_of_data_type(kind.Value.Value)
            key = label.split(".", 1)[1]
            array = label.startswith("write.") and key in ARRAY_KEYS
            is_array = variant is not None and isinstance(variant.Value, list | tuple)
            # an array variable a controller declared without filling it yet: its type and length are its own
            unset = variant is None or variant.Value is None or (is_array and not variant.Value)
            if label == "read.stage" and vtype == ua.VariantType.String and not is_array:
                continue  # the log's one text column (spec §3)
            if vtype not in numeric or (is_array != array and not (array and unset)):
                want = "an array of numbers" if array else "a number (a scalar)"
                got = (vtype.name if vtype is not None else "no value") + (" array" if is_array else "")
                raise CalibError(f"{label} = '{shown(name)}': the controller declares {got}; expected {want}")
            if array and not unset and len(variant.Value) != lengths.get(key, len(variant.Value)):
                raise CalibError(
                    f"{label} = '{shown(name)}': an array of {len(variant.Value)} on the controller; "
                    f"the estimate has {lengths[key]}"
                )
            if label.startswith("write."):
                self._writes.append((key, ua.NodeId.from_string(name), vtype))
        self._nodes = ids[: 1 + len(reads)] + ids[:1]

    def read(self) -> list[float]:
        values = self._run(self._client.uaclient.read_attributes(self._nodes, ua.AttributeIds.Value))
        out = []
        for value in values:
            if not value.StatusCode.is_good():
                raise LinkDown(f"a read returned {value.StatusCode.name}")
            out.append(value.Value.Value)
        return out

    def write(self, values: dict[str, Sequence[float] | float]) -> None:
        ids, data = [], []
        integral = {ua.VariantType.Float: float, ua.VariantType.Double: float}
        for key, node, vtype in self._writes:
            cast = integral.get(vtype, int)
            value = values[key]
            payload = [cast(v) for v in value] if isinstance(value, list | tuple) else cast(value)  # type: ignore[arg-type]
            ids.append(node)
            data.append(ua.DataValue(ua.Variant(payload, vtype)))
        try:
            results = self._run(self._client.uaclient.write_attributes(ids, data, ua.AttributeIds.Value))
        except ua.UaStatusCodeError as err:
            raise WriteFailed(_words(err)) from None
        for (key, _, _), status in zip(self._writes, results, strict=True):
            if not status.is_good():
                raise WriteFailed(f"write.{key}: {status.name}")

    def wait(self, seconds: float) -> None:
        self._run(asyncio.sleep(seconds))

    def close(self) -> None:
        try:
            self._loop.run_until_complete(asyncio.wait_for(self._client.disconnect(), 1.0))
        except Exception:  # a server already gone has nothing to say goodbye to
            pass
        finally:
            self._loop.close()


def _label(reads: dict[str, str], name: str) -> str:
    return "read." + next(column for column, node in reads.items() if node == name)


def _node_id(label: str, name: str):
    try:
        return ua.NodeId.from_string(name)
    except (ValueError, ua.UaStringParsingError, Exception):
        raise CalibError(
            f"{label} = '{shown(name)}': not an OPC UA node id; expected e.g. 'ns=2;s=Robot.Stroke1'"
        ) from None


def _variant_of_data_type(data_type) -> Any:
    """The variant type of a node whose value is empty, from its DataType (a built-in type's node id)."""
    try:
        return ua.VariantType(data_type.Identifier) if data_type.NamespaceIndex == 0 else None
    except (ValueError, AttributeError):
        return None


def _connection_status(err) -> bool:
    name = getattr(err, "code_as_name", lambda: "")()
    return any(word in name for word in ("Connection", "Session", "SecureChannel", "Timeout", "Shutdown", "Server"))


def _words(err: BaseException) -> str:
    text = str(err).strip() or type(err).__name__
    return text.splitlines()[0]
