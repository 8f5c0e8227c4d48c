# The two commands of README.md, and setup alone.
.PHONY: demo test setup
demo:
	tools/demo.sh
test:
	tools/run_tests.sh
setup:
	tools/setup.sh
