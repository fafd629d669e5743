"""Recordings and what is done with them: reading and writing, replay through an observer,
identification, flying start and gains tables. Private: the public names are re-exported by
`pmsmjax`."""
