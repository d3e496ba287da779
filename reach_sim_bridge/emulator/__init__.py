"""The virtual arm's firmware, its serial (pty) and UDP servers, faults and recording."""
