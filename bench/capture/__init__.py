"""Getting scenes in and out: `stgs prepare` on raw footage, and the interchange formats."""
