"""stgs.client: the reference ABR player (`stgs play`, issue 5)."""
