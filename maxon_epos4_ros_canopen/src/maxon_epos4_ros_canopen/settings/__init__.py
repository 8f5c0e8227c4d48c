"""``epos4_settings``: back up, compare and restore an EPOS4's settings over CAN.

    epos4_settings backup  DEVICE NODE [--dcf FILE] > node1.dcf
    epos4_settings diff    DEVICE NODE FILE
    epos4_settings restore DEVICE NODE FILE [--store]

The object list, the data types and the file format are canopen's: the DCF
or EDS is read with ``canopen.import_od``, every transfer is canopen's SDO
client (expedited or segmented, as the object needs), and the backup is
written with ``canopen.export_od``. What this module adds is the field
tool's judgement: which objects are settings, the order a drive accepts
them in, and the checks that keep it off a bus another master is driving.
docs/epos4_settings.md is the user's page.

Where each part is: dcf.py (the file, its settings, values as text),
session.py (the listen window, the SDO session, the checks), commands.py
(backup, diff, restore), cli.py (the command line).

Exit status: 0 done (diff: no difference); 1 done, with differences (diff)
or with objects the drive refused (backup, restore); 2 refused to run or
failed (bad arguments, another master on the bus, no answer, wrong product).
"""
from __future__ import annotations

from .cli import DEFAULT_LISTEN_S, DEFAULT_SDO_TIMEOUT_S, build_parser, main, shipped_dcf
from .commands import Difference, Progress, Writer, backup, compare, diff, restore, write_pdo
from .dcf import (BUS_IDENTITY, COMMANDS, PROG, REFUSE_READ, REFUSE_WRITE, SettingsError, SettingsFile,
                  load_file, settings)
from .session import DRAIN_LIMIT, Heard, Session, listen

__all__ = ["BUS_IDENTITY", "COMMANDS", "DEFAULT_LISTEN_S", "DEFAULT_SDO_TIMEOUT_S", "DRAIN_LIMIT", "PROG",
           "REFUSE_READ", "REFUSE_WRITE", "Difference", "Heard", "Progress", "Session", "SettingsError",
           "SettingsFile", "Writer", "backup", "build_parser", "compare", "diff", "listen", "load_file", "main",
           "restore", "settings", "shipped_dcf", "write_pdo"]
