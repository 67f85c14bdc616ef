"""The simulator's scenarios: package data, read with guard_sim.scenario. This folder installs as the
package guard_sim.scenarios."""
