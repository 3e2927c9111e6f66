# Thin aliases for ./dev.sh, which does the set-up (make may not exist on a fresh machine).
.PHONY: demo test bench setup
demo test bench setup:
	./dev.sh $@
