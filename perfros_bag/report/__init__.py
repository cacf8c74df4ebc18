"""Pictures and the HTML report: characterisation and fit PNGs, one self-contained page."""
