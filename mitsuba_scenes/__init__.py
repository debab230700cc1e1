"""Mitsuba 3 thin-lens references for the card scenes (not built yet; see the open Mitsuba issue)."""
