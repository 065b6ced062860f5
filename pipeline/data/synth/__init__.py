"""Procedural indoor scenes rendered with Mitsuba 3 into the InteriorVerse layout."""
