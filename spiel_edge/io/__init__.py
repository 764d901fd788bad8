"""Recorded acquisitions in and out (spiel-csv folders; MCAP lives in outputs/)."""
