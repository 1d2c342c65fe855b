"""stop_on_sigterm: SIGTERM and Ctrl-C stop a command, even when the signal lands where Python drops exceptions."""

import subprocess
import sys
import textwrap

import pytest

# Sends the signal to itself from inside a garbage-collector callback (JAX keeps one registered, and a long run
# collects often), where an exception raised by the handler would be printed and dropped; then works on for 3 s.
STOPPED_INSIDE_GC = textwrap.dedent("""
    import gc, os, signal, sys, time
    from pixelmpc_jax import host
    signal.signal(signal.SIGINT, signal.default_int_handler)  # as from a terminal: a background job ignores Ctrl-C
    host.stop_on_sigterm()
    signum = getattr(signal, sys.argv[1])

    def callback(phase, info):
        if phase == "start" and not fired:
            fired.append(True)
            os.kill(os.getpid(), signum)
            deadline = time.monotonic() + 0.05
            while time.monotonic() < deadline:  # the handler runs here, inside the callback
                time.sleep(0.001)

    fired = []
    gc.callbacks.append(callback)
    try:
        gc.collect()
        gc.callbacks.remove(callback)
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline:
            time.sleep(0.01)
        print("ran on")
    except KeyboardInterrupt as stop:
        print("stopped:", stop)
""")


@pytest.mark.parametrize("signame", ["SIGTERM", "SIGINT"])
def test_a_signal_inside_a_gc_callback_still_stops_the_command(signame):
    done = subprocess.run([sys.executable, "-c", STOPPED_INSIDE_GC, signame], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == f"stopped: signal {signame}", (done.stdout, done.stderr)
