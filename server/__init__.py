"""The animstudy service: configuration and command line (the web API arrives with the study-server issue)."""
