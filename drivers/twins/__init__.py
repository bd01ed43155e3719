"""Simulated twins: protocol peers that sit behind the transport, so real driver code runs.

`MecomTwin` answers MeCom on a pseudo-terminal and records every channel's emission over time;
`AptTwin` answers APT with motion that takes time on a clock the test controls. Both inject
faults (no reply, garbage, bad CRC or error replies, the port vanishing).
"""
