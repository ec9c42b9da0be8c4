# issue 24: a simulated study (2 subjects x 3 days x 2 poses x 2 filters) -> fluxmap study
study: $(VENV)/.installed
	$(PY) pipelines/study.py
.PHONY: study
