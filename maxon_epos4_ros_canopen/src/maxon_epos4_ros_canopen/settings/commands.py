"""The commands of epos4_settings: backup, diff and restore, on a Session
(session.py), with a progress line on stderr."""
from __future__ import annotations

import os
import time
from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence, TextIO, Tuple

from canopen.objectdictionary import ODVariable
from canopen.objectdictionary import datatypes as dt
from canopen.sdo.exceptions import SdoAbortedError

from .. import cia402
from .dcf import (BUS_IDENTITY, COB_INVALID, IDENTITY_PRODUCT, IDENTITY_REVISION, IDENTITY_VENDOR,
                  MAPPING_OFFSET, PDO_COUNT, PROG, RPDO_COMM, SAVE_SIGNATURE, STATUSWORD, STORE_PARAMETERS,
                  TPDO_COMM, Key, SettingsError, SettingsFile, abort_text, backup_skip, dcf_text, decode, encode,
                  export_dcf, find, key_of, restore_skip, settings, shown, variables, where)
from .session import Session

# Abort codes that will not change on a second try.
_FINAL_ABORTS = frozenset({0x06010000, 0x06010001, 0x06010002, 0x06020000, 0x06090011, 0x06070010})


class Progress:
    """One status line on ``stream`` (stderr): a bar redrawn in place on a
    terminal, a line every tenth of the way in a log. Hand-written: one
    line does not warrant a new dependency."""

    WIDTH = 30

    def __init__(self, stream: TextIO, label: str, total: int) -> None:
        self.stream = stream
        self.label = label
        self.total = max(1, total)
        self.done = 0
        self.tty = bool(getattr(stream, "isatty", lambda: False)())
        self._tenth = -1

    def step(self, what: str = "") -> None:
        self.done += 1
        if self.tty:
            filled = self.WIDTH * self.done // self.total
            self.stream.write("\r%s [%s%s] %d/%d %-40.40s" % (self.label, "#" * filled, "." * (self.WIDTH - filled),
                                                               self.done, self.total, what))
            self.stream.flush()
        else:
            tenth = 10 * self.done // self.total
            if tenth != self._tenth:
                self._tenth = tenth
                self.stream.write("%s: %d/%d\n" % (self.label, self.done, self.total))

    def close(self) -> None:
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()


def backup(session: Session, out: TextIO, err: TextIO) -> int:
    """Read every readable object the file lists; write a DCF to ``out``."""
    file = session.file
    identity = session.check_identity(refuse=True)
    session.check_consumers()
    todo = [v for v in variables(file.od) if backup_skip(v, file.flags) is None]
    refused: List[str] = []
    progress = Progress(err, "backup node %d" % session.node_id, len(todo))
    started = session.clock.now()
    try:
        for var in variables(file.od):
            var.value_raw = None
            if backup_skip(var, file.flags) is not None:
                var.value = None
                continue
            try:
                value = session.read(var)
            except SdoAbortedError as exc:
                refused.append("%s: %s" % (where(var), abort_text(exc)))
                var.value = None
            else:
                var.value = value
                var.value_raw = dcf_text(var, value)
            progress.step(where(var))
    finally:
        progress.close()
    elapsed = session.clock.now() - started
    info = file.od.device_information
    info.vendor_number = identity.get(IDENTITY_VENDOR, info.vendor_number)
    info.product_number = identity.get(IDENTITY_PRODUCT, info.product_number)
    info.revision_number = identity.get(IDENTITY_REVISION, info.revision_number)
    file.od.node_id = session.node_id
    file.od.comments = "\n".join([
        "Backup of node %d on %s by %s, %s UTC" % (session.node_id, session.device, PROG,
                                                   time.strftime("%Y-%m-%d %H:%M", time.gmtime(session.clock.wall()))),
        "Objects as listed by %s" % os.path.basename(file.path),
        "Identity (0x1018): %s" % ", ".join("sub %d 0x%08X" % (key[1], value)
                                            for key, value in sorted(identity.items())),
        "Objects the drive refused to read: %d (no ParameterValue)" % len(refused)])
    out.write(export_dcf(file, "backup of node %d on %s by %s" % (session.node_id, session.device, PROG)))
    out.flush()
    for line in refused:
        err.write("%s: not read, %s\n" % (PROG, line))
    err.write("%s: backup of node %d: %d objects read, %d refused, %d SDO transfers in %.2f s\n"
              % (PROG, session.node_id, len(todo) - len(refused), len(refused), session.transfers, elapsed))
    return 1 if refused else 0




@dataclass
class Difference:
    var: ODVariable
    drive: object  # the value read, or the SdoAbortedError of the read
    file: object


def compare(session: Session, candidates: Sequence[ODVariable], progress: Progress) -> List[Difference]:
    """The settings among ``candidates`` whose value on the drive differs
    from the file's (bytes on the wire compared), and those it refused to read."""
    found = []
    for var in candidates:
        try:
            data = session.upload(var)
        except SdoAbortedError as exc:
            found.append(Difference(var, exc, var.value))
        else:
            try:
                same = data == encode(var, var.value)
            except Exception:  # the file's value does not fit the type: it differs
                same = False
            if not same:
                found.append(Difference(var, decode(var, data), var.value))
        progress.step(where(var))
    progress.close()
    return found


def difference_line(d: Difference) -> str:
    note = BUS_IDENTITY.get(d.var.index)
    drive = "refused the read: %s" % abort_text(d.drive) if isinstance(d.drive, SdoAbortedError) \
        else "drive %s" % shown(d.var, d.drive)
    return "0x%04X sub %d  %s: %s, file %s%s" % (d.var.index, d.var.subindex, d.var.name, drive,
                                                shown(d.var, d.file), " (restore leaves it: %s)" % note
                                                if note else "")


def diff(session: Session, out: TextIO, err: TextIO) -> int:
    session.check_identity(refuse=True)
    session.check_consumers()
    if session.file.node_id not in (None, session.node_id):
        err.write("%s: note: %s was made for node %d, the drive is node %d\n"
                  % (PROG, session.file.path, session.file.node_id, session.node_id))
    candidates = settings(session.file)
    found = compare(session, candidates, Progress(err, "diff node %d" % session.node_id, len(candidates)))
    for d in found:
        out.write(difference_line(d) + "\n")
    err.write("%s: %d of %d settings differ (%d SDO transfers)\n"
              % (PROG, len(found), len(candidates), session.transfers))
    return 1 if found else 0


def pdo_of(index: int) -> Optional[int]:
    """The communication index of the PDO ``index`` configures, or None."""
    for base in (RPDO_COMM, TPDO_COMM):
        for n in range(PDO_COUNT):
            if index in (base + n, base + n + MAPPING_OFFSET):
                return base + n
    return None


class Writer:
    """Writes with a report of each refusal; remembers what it wrote."""

    def __init__(self, session: Session, progress: Progress) -> None:
        self.session = session
        self.progress = progress
        # key -> (variable, value, abort code or None, the report's line)
        self.refused: Dict[Key, Tuple[ODVariable, object, Optional[int], str]] = {}
        self.written: Dict[Key, ODVariable] = {}

    def write(self, var: ODVariable, value: object) -> bool:
        key = key_of(var)
        try:
            data = encode(var, value)
        except Exception as exc:  # struct.error, ValueError, TypeError: a value the type cannot hold
            self.refused[key] = (var, value, None, "not written %s = %s: the file's value does not fit its "
                                 "data type (%s)" % (where(var), shown(var, value), exc))
            self.progress.step(where(var))
            return False
        try:
            self.session.download(var, data)
        except SdoAbortedError as exc:
            self.refused[key] = (var, value, exc.code, "refused %s = %s: %s"
                                 % (where(var), shown(var, value), abort_text(exc)))
            return False
        finally:
            self.progress.step(where(var))
        self.refused.pop(key, None)
        self.written[key] = var
        return True


def restore(session: Session, out: TextIO, err: TextIO, store: bool) -> int:
    file = session.file
    session.check_identity(refuse=True)
    session.check_consumers()
    if file.node_id not in (None, session.node_id):
        raise SettingsError("%s was made for node %d (its COB-IDs and node-ID carry that node's values); "
                            "the drive is node %d: restore refuses to copy them onto another node"
                            % (file.path, file.node_id, session.node_id))
    statusword = find(file.od, STATUSWORD)
    if statusword is not None:
        try:
            state = cia402.state_or_none(int(session.read(statusword)))  # type: ignore[call-overload]
        except SdoAbortedError as exc:
            raise SettingsError("node %d refused to read its statusword (%s): restore cannot tell whether the "
                                "power stage is off, and writes motor and control data only when it is"
                                % (session.node_id, abort_text(exc))) from None
        if state in (cia402.State.SWITCHED_ON, cia402.State.OPERATION_ENABLED,
                     cia402.State.QUICK_STOP_ACTIVE, cia402.State.FAULT_REACTION_ACTIVE):
            raise SettingsError("node %d is %s: its power stage is on, and restore writes motor and control "
                                "data. Disable the drive first (the driver's halt and shutdown, or controlword "
                                "0x0006), then run again." % (session.node_id, state.value.replace("_", " ")))
    session.node.nmt.state = "PRE-OPERATIONAL"
    candidates = [v for v in settings(file) if restore_skip(v, file.flags) is None]
    found = compare(session, candidates, Progress(err, "restore node %d: read" % session.node_id, len(candidates)))
    plain = [d.var for d in found if pdo_of(d.var.index) is None]
    pdos = sorted({pdo_of(d.var.index) for d in found} - {None})  # type: ignore[type-var]
    pdo_vars = {comm: [v for v in candidates if pdo_of(v.index) == comm] for comm in pdos}
    total = len(plain) + sum(len(v) + 3 for v in pdo_vars.values()) + (1 if store else 0)
    progress = Progress(err, "restore node %d: write" % session.node_id, total)
    writer = Writer(session, progress)
    for var in plain:
        writer.write(var, var.value)
    for var, value, code, _ in list(writer.refused.values()):
        if code is not None and code not in _FINAL_ABORTS:  # an object written since may have made room for it
            writer.write(var, value)
    for comm in pdos:
        write_pdo(writer, file, comm, pdo_vars[comm])
    mismatched = []
    for key, var in sorted(writer.written.items()):
        try:
            data = session.upload(var)
        except SdoAbortedError:
            continue
        if data != encode(var, var.value):
            mismatched.append("%s: accepted %s but reads back %s"
                              % (where(var), shown(var, var.value), shown(var, decode(var, data))))
    stored = None
    if store:
        save = find(file.od, STORE_PARAMETERS)
        if save is None:
            save = ODVariable("Save all parameters", *STORE_PARAMETERS)
            save.data_type = dt.UNSIGNED32
            save.access_type = "rw"
        stored = writer.write(save, SAVE_SIGNATURE)
    progress.close()
    for _, _, _, line in writer.refused.values():
        out.write(line + "\n")
    for line in mismatched:
        out.write("not taken %s\n" % line)
    out.write("node %d: %d settings differed, %d written, %d refused%s; the drive is pre-operational\n"
              % (session.node_id, len(found), len(writer.written) - (1 if stored else 0),
                 len(writer.refused) + len(mismatched),
                 "; stored with 0x1010 (survives a power cycle)" if stored else
                 "; NOT stored (0x1010 save refused: lost at power-off)" if store else
                 "; not stored (lost at power-off; --store keeps it)"))
    err.write("%s: %d SDO transfers\n" % (PROG, session.transfers))
    return 1 if writer.refused or mismatched else 0


def write_pdo(writer: Writer, file: SettingsFile, comm: int, pdo_vars: Sequence[ODVariable]) -> None:
    """One PDO the CiA 301 way: invalidate its COB-ID, write the other
    communication parameters, clear the mapping count, write the entries,
    set the count, then the COB-ID as the file has it (valid or not)."""
    mapping = comm + MAPPING_OFFSET
    cob = find(file.od, (comm, 1))
    count = find(file.od, (mapping, 0))
    if cob is None or cob.value is None or count is None or count.value is None:
        for var in pdo_vars:
            writer.write(var, var.value)  # no COB-ID or count in the file: as the file has them
        return
    cob_value = int(cob.value)  # type: ignore[call-overload]
    writer.write(cob, cob_value | COB_INVALID)
    for var in pdo_vars:
        if var.index == comm and var.subindex != 1:
            writer.write(var, var.value)
    writer.write(count, 0)
    for var in pdo_vars:
        if var.index == mapping and var.subindex != 0:
            writer.write(var, var.value)
    if writer.write(count, count.value):
        writer.write(cob, cob_value)
    elif not cob_value & COB_INVALID:
        writer.session.err.write("%s: 0x%04X left invalid: its mapping count was refused\n" % (PROG, comm))


