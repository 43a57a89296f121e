"""stgs.packager: model dir -> MPEG-DASH tree (`stgs pack`, issue 3)."""
