"""guard_sim: a SITL-like ground vehicle that speaks MAVLink 2 (and DroneCAN), with attack injection.

Its source is the folder sim/; it installs as the package guard_sim (`from guard_sim.run import run`).

The simulator is the vehicle side. It imports nothing from `guard`: it talks to guard only through
MAVLink bytes, CAN frames and files, exactly like a real autopilot would.
"""
