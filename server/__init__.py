"""The animstudy service: settings, database, the study API and pages, media, and the command line."""
