"""What to fetch and how: the sans-IO fetch schedule (`schedule`, speaking the vocabulary of `steps`) with its
retries (`retry`) and recovery paths, and the HTTP downloader that performs its requests (`download`)."""
