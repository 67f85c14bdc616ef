"""The configs shipped with guard (guard.toml, the profiles, the systemd unit): package data, read with
guard.resources. This folder installs as the package guard.configs."""
