"""Virtual maxon EPOS4: CiA 301/402 drive simulator on any python-can bus.

``Simulator(bus, [NodeConfig(1, "epos4_node1.dcf")]).start()`` serves the
nodes in a background thread; ``main()`` is the command-line program.
"""
from .drive import VirtualEpos4
from .runner import NodeConfig, Simulator, parse_node_spec
from .cli import main

__all__ = ["VirtualEpos4", "NodeConfig", "Simulator", "parse_node_spec", "main"]
