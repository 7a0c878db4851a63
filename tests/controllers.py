"""Controllers for the link tests (spec §16): real servers inside the test's process, on 127.0.0.1.

:class:`OpcUaController` is an ``asyncua`` server; :class:`AdsController` pyads's ADS test server
with its ``AdvancedHandler``. Each publishes a log's rows one by one under a sample counter, as a
controller's cycle would, and holds the variables ``[write]`` names for the estimate handed back.

``handshake=True`` publishes the next row only once a whole read request has seen the last one
(the counter is read twice in every poll): every row is read, whatever the machine's load, so a
test can compare the estimate with ``calibrate`` on the same rows without a timed assert.
"""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import logging
import socket
import struct
import tempfile
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

#: the variable names a PLC program declares (docs/howto/controller.md uses the same).
PREFIX = "Robot."


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def link_toml(
    url: str, names: dict[str, str], sample: str | None, writes: dict[str, str], rate_hz: float = 500.0
) -> str:
    lines = ["[link]", f'url = "{url}"', f"rate_hz = {rate_hz}"]
    if sample is not None:
        lines.append(f'sample = "{sample}"')
    lines += ["[read]", *(f'{column} = "{name}"' for column, name in names.items())]
    if writes:
        lines += ["[write]", *(f'{key} = "{name}"' for key, name in writes.items())]
    return "\n".join(lines) + "\n"


class OpcUaController:
    """An OPC UA server on 127.0.0.1 that publishes rows (``columns`` → values) under a counter.

    Args:
        columns: the log columns it publishes, each a Double variable ``ns=2;s=Robot.<column>``.
        lengths: the Double arrays it holds for the estimate (``Calib.<key>``); ``samples_used`` an Int32.
        types: variant type names of some columns instead of Double (a wrong type, for the refusals).
    """

    def __init__(self, columns: list[str], lengths: dict[str, int], types: dict[str, str] | None = None):
        from asyncua import Server, ua

        self.ua, self.columns, self.port = ua, columns, free_port()
        self.url = f"opc.tcp://127.0.0.1:{self.port}/"
        self._loop = asyncio.new_event_loop()
        logging.getLogger("asyncua").setLevel(logging.ERROR)  # its notes on a test server without security
        self._server = Server()
        self._lengths, self._types = lengths, types or {}
        self.handed_back = HandedBack()
        self.reads = 0  # read requests that saw the counter (each poll reads it twice)
        self.counter = 0
        self._seen = asyncio.Event()
        self._thread = threading.Thread(target=self._loop.run_forever, daemon=True)
        self._thread.start()
        self._call(self._setup())

    def _call(self, coroutine):
        # longer than a handshake's own wait for the poll (_drained, 60 s): on a loaded machine that wait
        # decides, with its own error, not this one's bare TimeoutError
        return asyncio.run_coroutine_threadsafe(coroutine, self._loop).result(timeout=90)

    def node(self, name: str) -> str:
        return f"ns={self.ns};s={name}"

    async def _setup(self) -> None:
        ua = self.ua
        await self._server.init()
        self._server.set_endpoint(self.url)
        self._server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
        self.ns = await self._server.register_namespace("urn:stewart-calib:test-controller")
        robot = await self._server.nodes.objects.add_object(self.ns, "Robot")
        self._nodes = {}
        for column in self.columns:
            vtype = getattr(ua.VariantType, self._types.get(column, "Double"))
            zero = (
                False
                if vtype == ua.VariantType.Boolean
                else (0.0 if "Float" in vtype.name or "Double" in vtype.name else 0)
            )
            self._nodes[column] = await robot.add_variable(
                ua.NodeId(PREFIX + column, self.ns), column, ua.Variant(zero, vtype)
            )
        self._counter = await robot.add_variable(
            ua.NodeId(PREFIX + "Sample", self.ns), "Sample", ua.Variant(0, ua.VariantType.Int64)
        )
        # every read of the counter is counted: the handshake of publish(), and nothing else changes
        self._server.iserver.aspace.set_attribute_value_callback(
            self._counter.nodeid, ua.AttributeIds.Value, self._counter_read
        )
        # a variable of another type, for the refusals
        await robot.add_variable(
            ua.NodeId(PREFIX + "Name", self.ns), "Name", ua.Variant("hexapod", ua.VariantType.String)
        )
        calib = await self._server.nodes.objects.add_object(self.ns, "Calib")
        self._writes = {}
        for key, length in self._lengths.items():
            value = ua.Variant([0.0] * length, ua.VariantType.Double)
            if key == "samples_used":
                value = ua.Variant(0, ua.VariantType.Int32)
            self._writes[key] = node = await calib.add_variable(ua.NodeId("Calib." + key, self.ns), key, value)
            await node.set_writable()
        if "samples_used" in self._writes:
            self._server.iserver.aspace.set_attribute_value_setter(
                self._writes["samples_used"].nodeid, ua.AttributeIds.Value, self._samples_used_written
            )
        await self._server.start()

    def _samples_used_written(self, node, attr, value) -> None:
        node.attributes[attr].value = value
        self.handed_back.record(value.Value.Value)

    def _counter_read(self, nodeid, attr):
        self.reads += 1
        if self.reads >= self._wanted:
            self._seen.set()
        return self.ua.DataValue(self.ua.Variant(self.counter, self.ua.VariantType.Int64))

    _wanted = 0

    def link(self, writes: Iterable[str] = (), rate_hz: float = 500.0, names: dict[str, str] | None = None) -> str:
        names = names or {column: self.node(PREFIX + column) for column in self.columns}
        return link_toml(
            self.url, names, self.node(PREFIX + "Sample"), {k: self.node("Calib." + k) for k in writes}, rate_hz
        )

    async def _publish(self, values: Iterable[float], counter: int, handshake: bool) -> None:
        ua = self.ua
        await self._drained()
        for column, value in zip(self.columns, values, strict=True):
            vtype = getattr(ua.VariantType, self._types.get(column, "Double"))
            await self._server.write_attribute_value(
                self._nodes[column].nodeid, ua.DataValue(ua.Variant(float(value), vtype))
            )
        # no await has suspended since the first write: a read request sees all of this sample or none
        self.counter = counter
        if handshake:
            self._seen.clear()
            self._wanted = self.reads + 2  # a whole poll (counter, values, counter) after this one

    async def _drained(self) -> None:
        if self.reads < self._wanted:
            await asyncio.wait_for(self._seen.wait(), 60)

    def publish(self, values: Iterable[float], counter: int, handshake: bool = True) -> None:
        """Publish a sample, once a poll has seen the last one published with ``handshake``."""
        self._call(self._publish(list(values), counter, handshake))

    def drain(self) -> None:
        """Wait until a poll has seen the last sample published with ``handshake``."""
        self._call(self._drained())

    def written(self, key: str):
        return self._call(self._writes[key].read_value())

    async def _drop_the_network(self) -> None:
        listening = self._server.bserver
        # no connection is accepted from here on, then the open ones are dropped. asyncua's own
        # stop drops them first and stops listening after: a link reconnecting at once could be
        # accepted in between, and that stop then waited for its connection to end (the link
        # reading on, no gap seen)
        listening._server.close()
        await listening.stop()

    def stop(self) -> None:
        """The network goes down: the link's connection is dropped and no new one accepted. The
        controller's address space and cycle go on (asyncua's whole server stop would also wait
        up to 1 s for its clock task, the link down that much longer)."""
        self._call(self._drop_the_network())

    def restart(self) -> None:
        """The network is back: connections are accepted again."""
        self._call(self._server.bserver.start())

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self._call(self._server.stop())
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(10)


class HandedBack:
    """How often and when the link wrote ``samples_used`` into the controller: the benchmark's clock."""

    def __init__(self) -> None:
        self.count, self.value, self.at = 0, 0, 0.0
        self._changed = threading.Condition()

    def record(self, value: int) -> None:
        with self._changed:
            self.count, self.value, self.at = self.count + 1, value, time.perf_counter()
            self._changed.notify_all()

    def wait_for(self, count: int, timeout_s: float) -> float | None:
        """The time of the ``count``-th write (None: not within ``timeout_s``)."""
        with self._changed:
            if self._changed.wait_for(lambda: self.count >= count, timeout_s):
                return self.at
        return None


def publisher(controller, rows: np.ndarray, first_counter: int = 1, skip: Callable[[int], bool] = lambda k: False):
    """Publish ``rows`` one by one (counter ``first_counter`` up), the first at once and the others
    from a thread, each once the link has seen the one before; rows ``k`` with ``skip(k)`` are never
    published (their counter values are jumped over). Returns the thread (it ends when the link
    has seen the last row)."""
    ks = [k for k in range(len(rows)) if not skip(k)]
    controller.publish(rows[ks[0]], first_counter + ks[0])

    def run() -> None:
        for k in ks[1:]:
            controller.publish(rows[k], first_counter + k)
        controller.drain()

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


# ------------------------------------------------------------------------------------------- ADS
#: the ADS test server's port is fixed by the client library (48898): one test at a time uses it.
ADS_LOCK = Path(tempfile.gettempdir()) / "stewart-calib-ads-test-server.lock"
ADS_NET_ID = "127.0.0.1.1.1"


class AdsController:
    """pyads's ADS test server on 127.0.0.1 with LREAL variables ``Robot.<column>``, a UDINT
    ``Robot.Sample`` and LREAL arrays ``Calib.<key>`` (``Calib.samples_used`` a DINT).

    An unknown name is answered with ADS error 1808 (symbol not found), as TwinCAT answers it (the
    stock handler raises inside its thread, and the client would wait for its timeout)."""

    def __init__(self, columns: list[str], lengths: dict[str, int], types: dict[str, str] | None = None):
        import pyads
        from pyads import constants
        from pyads.testserver import AdsTestServer, AdvancedHandler, PLCVariable

        self._lock = open(ADS_LOCK, "w")
        fcntl.flock(self._lock, fcntl.LOCK_EX)
        self.pyads, self.columns = pyads, columns
        self.reads = 0
        self.lock = threading.Lock()
        outer = self

        class Handler(AdvancedHandler):
            def handle_request(self, request):
                command = struct.unpack("<H", request.ams_header.command_id)[0]
                data = request.ams_header.data
                group = struct.unpack("<I", data[:4])[0] if len(data) >= 4 else None
                with outer.lock:  # a PLC serves ADS between its cycles: a request sees one cycle's values
                    if command == constants.ADSCOMMAND_READWRITE and group == constants.ADSIGRP_SUMUP_READ:
                        outer.reads += 1
                    try:
                        return super().handle_request(request)
                    except KeyError:
                        return _ads_error(request, 1808)

        self.handler = Handler()
        types = types or {}
        self._vars = {}
        for column in columns:
            kind = types.get(column, "LREAL")
            ads_type = {"LREAL": constants.ADST_REAL64, "INT": constants.ADST_INT16}[kind]
            var = PLCVariable(PREFIX + column, 0.0 if kind == "LREAL" else 0, ads_type, kind)
            self.handler.add_variable(var)
            self._vars[column] = var
        self._counter = PLCVariable(PREFIX + "Sample", 0, constants.ADST_UINT32, "UDINT")
        self.handler.add_variable(self._counter)
        self._writes = {}
        for key, length in lengths.items():
            if key == "samples_used":
                var = PLCVariable("Calib." + key, 0, constants.ADST_INT32, "DINT")
            else:
                var = PLCVariable(
                    "Calib." + key, bytes(8 * length), constants.ADST_REAL64, f"ARRAY [1..{length}] OF LREAL"
                )
            self.handler.add_variable(var)
            self._writes[key] = var
        self.handed_back = HandedBack()
        if "samples_used" in self._writes:
            var, plain = self._writes["samples_used"], self._writes["samples_used"].write

            def write(value, request=None) -> None:
                plain(value, request)
                self.handed_back.record(struct.unpack("<i", var.value)[0])

            var.write = write
        self.server = AdsTestServer(handler=self.handler, ip_address="127.0.0.1", logging=False)
        self.server.start()
        self.url = f"ads://127.0.0.1/{ADS_NET_ID}:851"

    def link(self, writes: Iterable[str] = (), rate_hz: float = 500.0) -> str:
        names = {column: PREFIX + column for column in self.columns}
        return link_toml(self.url, names, PREFIX + "Sample", {k: "Calib." + k for k in writes}, rate_hz)

    def publish(self, values: Iterable[float], counter: int, handshake: bool = True) -> None:
        """Publish a sample, once a sum-read has seen the last one published with ``handshake``."""
        self.drain()
        with self.lock:  # one cycle: no request is served in the middle of it
            for column, value in zip(self.columns, values, strict=True):
                self._vars[column].value = struct.pack("<d", float(value))
            self._counter.value = struct.pack("<I", counter)
            if handshake:
                self._wanted = self.reads + 1  # a sum-read served after this cycle

    _wanted = 0

    def drain(self) -> None:
        for _ in range(60_000):
            if self.reads >= self._wanted:
                return
            threading.Event().wait(0.001)
        raise TimeoutError("the link did not poll the ADS test server")

    def written(self, key: str):
        var = self._writes[key]
        if key == "samples_used":
            return struct.unpack("<i", var.value)[0]
        return list(struct.unpack(f"<{len(var.value) // 8}d", var.value))

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.server.stop()
            self.server.join(5)  # its listening socket is free only once its loop has ended
        fcntl.flock(self._lock, fcntl.LOCK_UN)
        self._lock.close()


def _ads_error(request, code: int):
    from pyads.testserver.testserver import AmsResponseData

    state = struct.unpack("<H", request.ams_header.state_flags)[0] | 0x0001
    return AmsResponseData(struct.pack("<H", state), request.ams_header.error_code, struct.pack("<II", code, 0))
