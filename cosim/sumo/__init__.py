"""SUMO and the net: the libsumo session (`session`, the only module that imports libsumo) and the `Snapshot`
it takes each step (`snapshot`), the net (`roadnet` parses the .net.xml, `netdesc` says what its edges mean,
`net` joins them with the geometry along the route), an episode's routes (`scenario`) and SUMO's output files
(`outputs`)."""
