"""What the driver knows of its nodes before any frame, and its timeouts.

``NodeTable`` is built once from the configuration (every node's DCF/EDS
read and its PDO plan checked) and never changes after: every thread may
read it. ``Timeouts`` are the user's settings, read at each use."""
from __future__ import annotations

import logging
import os
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, Callable, Dict, ItemsView, Iterator, NamedTuple, Optional, Sequence, Tuple, ValuesView

import canopen

from ..clock import Clock
from ..config_schema import DEFAULT_SHUTDOWN_TIMEOUT, ConfigError, DriverConfig
from ..objects import load_dictionary
from ..result import Result, fail
from .convert import Converter
from .pdo import PdoLayoutError, RxPdo, TxPdo, enabled_maps
from .plan import NodePlan, plan_node

log = logging.getLogger("maxon_epos4_ros_canopen.driver")


class Node(NamedTuple):
    """One node: configuration, dictionary, plan and command converter."""
    cfg: Any
    od: Any
    plan: NodePlan
    converter: Converter   # commands to device units (immutable)


@dataclass
class Timeouts:
    """Seconds. An EPOS4 answers an SDO within a millisecond; the generous
    SDO timeout is for loaded hosts (and user-mode Linux), it only delays
    the error about a node that is really gone."""
    sdo: float = 1.0
    boot: float = 5.0
    state: float = 5.0
    homing: float = 60.0
    cycle_join: float = 5.0  # how long shutdown waits for the cycle thread to end
    # shutdown and close as a whole: every SDO step of it gets only the time
    # left, the steps that stop drives by PDO and NMT run whatever is left
    shutdown: float = DEFAULT_SHUTDOWN_TIMEOUT


class NodeTable:
    """The configured nodes by name, in configuration order (immutable)."""

    def __init__(self, config: DriverConfig) -> None:
        nodes: "OrderedDict[str, Node]" = OrderedDict()
        # Planning reads the DCF's values, which depend on the node-ID
        # ($NODEID). After it only the objects' types and sizes are used,
        # the same for every node of one file: those nodes share the first
        # one's dictionary (about 160 kB each for an EPOS4 DCF).
        shared_ods: Dict[str, canopen.ObjectDictionary] = {}
        for n in config.nodes:
            try:
                od = load_dictionary(n.eds_file, n.node_id)
            except Exception as e:  # canopen raises many kinds on a bad file
                raise ConfigError(config.source, "nodes/%s/eds_file" % n.key,
                                  "cannot read %s: %s" % (n.eds_file, e)) from None
            plan = plan_node(n, od, config.sync, config.source, config.heartbeat)
            try:
                for m in enabled_maps(plan.rx):
                    RxPdo(od, m)
                for m in enabled_maps(plan.tx):
                    TxPdo(od, m)
            except PdoLayoutError as e:
                raise ConfigError(config.source, "nodes/%s/eds_file" % n.key, str(e)) from None
            od = shared_ods.setdefault(os.path.realpath(n.eds_file), od)
            nodes[n.name] = Node(n, od, plan, Converter(n, od))
        self._nodes = nodes
        self._by_key = {node.cfg.key: name for name, node in nodes.items()}

    def name(self, name: Any) -> Optional[str]:
        """A node's name from its name or its node key (``node1``)."""
        if not isinstance(name, str):
            return None
        if name in self._nodes:
            return name
        return self._by_key.get(name)

    def unknown(self, name: Any) -> Result:
        return fail("unknown node %r (known: %s)" % (name, ", ".join(self._nodes)))

    def __getitem__(self, name: str) -> Node:
        return self._nodes[name]

    def __contains__(self, name: object) -> bool:
        return name in self._nodes

    def __iter__(self) -> Iterator[str]:
        return iter(self._nodes)

    def __len__(self) -> int:
        return len(self._nodes)

    def items(self) -> ItemsView[str, Node]:
        return self._nodes.items()

    def values(self) -> ValuesView[Node]:
        return self._nodes.values()


class InitError(Exception):
    """A step of init or recover failed; the text names the node and the step."""


class StateTimeout(Exception):
    """A drive did not show what a service waited for (the text: what it shows)."""


_INIT_WORKERS = 32  # nodes configured at once: each has its own SDO client and lock


def each_node(nodes: NodeTable, names: Sequence[str], work: Callable[[str], Any], clock: Clock) -> Dict[str, Any]:
    """work(name) for every node at once; the results by name, or an
    InitError naming every node that failed (each message names the node
    and the step)."""
    results, errors = each_node_collect(nodes, names, work, clock)
    if errors:
        raise InitError("; ".join(errors[n] for n in names if n in errors))
    return results


def each_node_collect(nodes: NodeTable, names: Sequence[str], work: Callable[[str], Any],
                      clock: Clock) -> Tuple[Dict[str, Any], Dict[str, str]]:
    """work(name) for every node at once (the bus interleaves their SDO
    transfers; ``clock`` runs them: threads, or one after the other on a
    stepped clock): the results and the errors, by name."""
    results: Dict[str, Any] = {}
    errors: Dict[str, str] = {}

    def run(name: str) -> None:
        try:
            results[name] = work(name)
        except InitError as e:
            errors[name] = str(e)
        except Exception as e:  # a bus going away, anything: the node is named all the same
            log.exception("init of %s", name)
            errors[name] = "%s (node %d): %s" % (name, nodes[name].cfg.node_id, e)
    clock.run_each(run, list(names), _INIT_WORKERS)
    return results, errors
