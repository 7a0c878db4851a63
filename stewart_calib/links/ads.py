"""TwinCAT ADS controllers (``ads://HOST/AMS_NET_ID:PORT``), through ``pyads`` (the ``link`` extra).

Variables are the PLC's symbol names (``MAIN.fStroke1``, ``GVL_Robot.nSample``). At the start every
symbol's information is read once (its index group and offset, its ADS type and size: a missing
symbol or a type that is no number is refused there); a poll is then one ADS sum-read
(``ADSIGRP_SUMUP_READ``, the request under ``pyads``' ``read_list_by_name``) of the stamp, every
``[read]`` symbol and the stamp again — by index group and offset, the stamp twice, which
``read_list_by_name`` itself cannot do (it returns a dictionary by name). The estimate goes back in
one sum-write (``write_list_by_name``), each value packed as the symbol declares (an LREAL array, a
DINT). Port 851 is the first PLC runtime of TwinCAT 3 (801 under TwinCAT 2).
"""

from __future__ import annotations

import struct
import time
from collections.abc import Sequence
from urllib.parse import urlsplit

from ..errors import CalibError, shown
from . import ARRAY_KEYS, LinkDown, WriteFailed

try:
    import pyads
    from pyads.pyads_ex import adsGetSymbolInfo, adsSumReadBytes
except ImportError:  # the optional extra: said when a link is used, not at import
    pyads = None

#: ADS data types that hold a number, and their ``struct`` codes (little-endian).
_FORMATS = {
    16: "b",  # ADST_INT8
    17: "B",  # ADST_UINT8
    2: "h",  # ADST_INT16
    18: "H",  # ADST_UINT16
    3: "i",  # ADST_INT32
    19: "I",  # ADST_UINT32
    20: "q",  # ADST_INT64
    21: "Q",  # ADST_UINT64
    4: "f",  # ADST_REAL32
    5: "d",  # ADST_REAL64
    33: "?",  # ADST_BIT
}
#: ADS errors that mean the symbol is not there (as opposed to a connection that failed).
_NO_SYMBOL = {1808, 1809, 1810}  # symbol not found, invalid index group, invalid index offset


def connect(url: str, timeout_s: float) -> AdsConnection:
    if pyads is None:
        raise CalibError("link: an ADS link needs the pyads package (pip install 'stewart-calib[link]')")
    return AdsConnection(url, timeout_s)


def _address(url: str) -> tuple[str, str, int]:
    parts = urlsplit(url)
    net_id, _, port = parts.path.strip("/").partition(":")
    try:
        if not parts.hostname or len(net_id.split(".")) != 6 or not 0 < int(port) < 65536:
            raise ValueError
        for byte in net_id.split("."):
            if not 0 <= int(byte) < 256:
                raise ValueError
    except ValueError:
        raise CalibError(
            f"link.url = '{shown(url)}': expected ads://HOST/AMS_NET_ID:PORT (e.g. ads://192.168.1.10/5.12.34.56.1.1:851)"
        ) from None
    return parts.hostname, net_id, int(port)


class AdsConnection:
    """One ADS connection to a PLC runtime (see the module docstring)."""

    def __init__(self, url: str, timeout_s: float):
        host, net_id, port = _address(url)
        self._plc = pyads.Connection(net_id, port, host)
        try:
            self._plc.open()
            self._plc.set_timeout(int(timeout_s * 1000))
            self._plc.read_state()  # a router that takes the route opens without the PLC being there
        except (pyads.ADSError, OSError) as err:
            self.close()
            raise LinkDown(_words(err)) from None
        self._reads: list[tuple[int, int, int]] = []
        self._formats: list[str] = []
        self._writes: dict[str, str] = {}

    def _symbol(self, label: str, name: str):
        try:
            return adsGetSymbolInfo(self._plc._port, self._plc._adr, name)
        except pyads.ADSError as err:
            if err.err_code in _NO_SYMBOL:
                raise CalibError(
                    f"{label} = '{shown(name)}': not on the controller (ADS error {err.err_code}); "
                    "expected a symbol the PLC program declares"
                ) from None
            raise LinkDown(_words(err)) from None
        except OSError as err:
            raise LinkDown(_words(err)) from None

    def check(self, reads: dict[str, str], stamp: str, writes: dict[str, str], lengths: dict[str, int]) -> None:
        stamp_label = "link.sample" if stamp not in reads.values() else _label(reads, stamp)
        labelled = [(stamp_label, stamp), *((f"read.{column}", name) for column, name in reads.items())]
        for label, name in labelled + [(f"write.{key}", name) for key, name in writes.items()]:
            info = self._symbol(label, name)
            code = _FORMATS.get(info.dataType)
            key = label.split(".", 1)[1]
            array = label.startswith("write.") and key in ARRAY_KEYS
            count = info.size // struct.calcsize(code) if code else 0
            if code is None or (count != 1 and not array) or (array and count * struct.calcsize(code) != info.size):
                want = "an array of numbers" if array else "a number (a scalar)"
                raise CalibError(
                    f"{label} = '{shown(name)}': the controller declares {shown(info.symbol_type)}; expected {want}"
                )
            if array and count != lengths.get(key, count):
                raise CalibError(
                    f"{label} = '{shown(name)}': an array of {count} on the controller; the estimate has {lengths[key]}"
                )
            if label.startswith("write."):
                self._writes[key] = name
            else:
                self._reads.append((info.iGroup, info.iOffs, info.size))
                self._formats.append(code)
        self._reads.append(self._reads[0])
        self._formats.append(self._formats[0])
        self._layout = "<" + "I" * len(self._reads) + "".join(self._formats)

    def read(self) -> list[float]:
        try:
            data = adsSumReadBytes(self._plc._port, self._plc._adr, self._reads)
        except (pyads.ADSError, OSError) as err:
            raise LinkDown(_words(err)) from None
        values = struct.unpack_from(self._layout, bytes(data))
        errors = values[: len(self._reads)]
        if any(errors):
            raise LinkDown(f"a sum-read returned ADS error {next(e for e in errors if e)}")
        return [float(value) for value in values[len(self._reads) :]]

    def write(self, values: dict[str, Sequence[float] | float]) -> None:
        try:
            results = self._plc.write_list_by_name({name: values[key] for key, name in self._writes.items()})
        except pyads.ADSError as err:
            if err.err_code in (1861, 6, 7):  # timeout, target port or machine not found: the link is down
                raise LinkDown(_words(err)) from None
            raise WriteFailed(_words(err)) from None
        except OSError as err:
            raise LinkDown(_words(err)) from None
        failed = {name: status for name, status in results.items() if status != "no error"}
        if failed:
            raise WriteFailed("; ".join(f"{name}: {status}" for name, status in failed.items()))

    def wait(self, seconds: float) -> None:
        time.sleep(seconds)

    def close(self) -> None:
        try:
            self._plc.close()
        except (pyads.ADSError, OSError):  # a PLC already gone
            pass


def _label(reads: dict[str, str], name: str) -> str:
    return "read." + next(column for column, symbol in reads.items() if symbol == name)


def _words(err: BaseException) -> str:
    text = str(err).strip() or type(err).__name__
    return text.splitlines()[0]
