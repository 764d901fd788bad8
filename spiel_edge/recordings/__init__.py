"""Recordings: spiel-csv folders and MCAP files, read, scanned, written, recovered."""
