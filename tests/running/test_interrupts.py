"""A Ctrl-C that lands in a finalizer (pcfbench.interrupts): delivered again, with nothing printed."""

import os
import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent("""
    import os, signal, sys, time, weakref
    {install}
    class Thing:
        pass
    def finalizer(ref):
        os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C, while a weakref callback runs
        for _ in range(1000):  # a few bytecodes: Python runs the handler in here
            pass
    try:
        thing = Thing()
        ref = weakref.ref(thing, finalizer)
        del thing
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            pass
        print("not interrupted")
    except KeyboardInterrupt:
        print("interrupted")
    {after}
""")


def _run(install: str, after: str = "") -> subprocess.CompletedProcess:
    code = SCRIPT.format(install=install, after=after)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)


def test_python_alone_loses_a_ctrl_c_that_lands_in_a_finalizer():
    """The case the hook is for, as Python has it: printed, then lost."""
    out = _run("")
    assert out.stdout.strip() == "not interrupted"
    assert "Exception ignored in" in out.stderr and "KeyboardInterrupt" in out.stderr


def test_the_hook_delivers_it_again_and_prints_nothing():
    install = "from pcfbench.interrupts import redeliver_swallowed_interrupts as r; r(); r()"
    after = textwrap.dedent("""
        class Broken:
            def __del__(self):
                raise ValueError("a finalizer's own error")
        Broken()
        print("alarm handler restored:", signal.getsignal(signal.SIGALRM) is signal.SIG_DFL)
    """)
    out = _run(install, after)
    assert out.stdout.splitlines()[0] == "interrupted", out
    assert "alarm handler restored: True" in out.stdout
    assert "KeyboardInterrupt" not in out.stderr, out.stderr
    # every other unraisable exception is printed as Python prints it
    assert "Exception ignored in" in out.stderr and "ValueError: a finalizer's own error" in out.stderr


def _pcfbench(code: str) -> subprocess.CompletedProcess:
    """``code``, then the ``pcfbench`` command's entry point as the installed script calls it."""
    script = code + "\nimport sys\nfrom pcfbench.entry import main\nsys.argv = ['pcfbench', 'plugins']\nmain()\n"
    return subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)


def test_the_pcfbench_command_says_one_line_for_a_ctrl_c_before_or_in_a_command():
    """Ctrl-C while the command still imports its modules, or in a command that does not answer it
    itself: one line and exit status 130 (not a traceback through the imports, not click's
    "Aborted!" and status 1), and the hook is installed."""
    while_importing = _pcfbench(textwrap.dedent("""
        import sys
        class Interrupting:  # Ctrl-C while pcfbench.cli's modules import
            def find_spec(self, name, path=None, target=None):
                if name == "pcfbench.cli":
                    raise KeyboardInterrupt
        sys.meta_path.insert(0, Interrupting())
    """))
    assert (while_importing.returncode, while_importing.stderr) == (130, "\npcfbench: interrupted\n"), while_importing
    in_a_command = _pcfbench(textwrap.dedent("""
        import atexit, sys
        import pcfbench.cli
        real, calls = pcfbench.cli.get_plugins, []
        def interrupted():  # the first call adds the plugins' commands; the second is `pcfbench plugins`'s
            calls.append(1)
            if len(calls) > 1:
                raise KeyboardInterrupt
            return real()
        pcfbench.cli.get_plugins = interrupted
        atexit.register(lambda: print("hook:", getattr(sys.unraisablehook, "redelivers_interrupts", False)))
    """))
    assert (in_a_command.returncode, in_a_command.stderr) == (130, "\npcfbench: interrupted\n"), in_a_command
    assert in_a_command.stdout == "hook: True\n"


def test_an_interrupt_that_reached_its_handler_is_not_delivered_again():
    """The same Ctrl-C lost once in a finalizer and delivered once anyway: the command saying what it
    stopped (after ``handled``) is not interrupted by the redelivery."""
    code = textwrap.dedent("""
        import gc, signal, time
        from pcfbench.interrupts import handled, redeliver_swallowed_interrupts
        redeliver_swallowed_interrupts()
        class Loud:
            def __del__(self):
                raise KeyboardInterrupt  # lost: the hook arms the redelivery
        try:
            Loud()
            raise KeyboardInterrupt  # ... and the interrupt propagated anyway
        except KeyboardInterrupt:
            handled()
            deadline = time.monotonic() + 0.3
            while time.monotonic() < deadline:
                pass
            print("said what it stopped")
        print(signal.getsignal(signal.SIGALRM) is signal.SIG_DFL)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.stdout.splitlines() == ["said what it stopped", "True"], out
    assert out.stderr == ""


PROBE = textwrap.dedent("""
    import os, signal

    def init():
        pass

    def task(key):
        os.kill(os.getpid(), signal.SIGINT)  # a Ctrl-C reaching the worker mid-sample: the driver's to answer
        return key * 10

    def on_failure(key, kind, message):
        return (key, kind, message)
""")

DRIVER = textwrap.dedent("""
    import multiprocessing.forkserver, multiprocessing.resource_tracker, os, signal, time
    import probe
    from pcfbench.running import workers

    workers._context()  # starts the resource tracker and the forkserver, and returns at once
    # (private attributes: the helpers' pids, to send them what a terminal's Ctrl-C sends them)
    helpers = [multiprocessing.forkserver._forkserver._forkserver_pid,
               multiprocessing.resource_tracker._resource_tracker._pid]
    for pid in helpers:  # while each is still starting Python, or importing the forkserver's preloads
        os.kill(pid, signal.SIGINT)
    print(sorted(workers.run_supervised([1, 2, 3], 2, probe.init, (), probe.task, probe.on_failure)))
    print([os.waitpid(pid, os.WNOHANG) == (0, 0) for pid in helpers])  # both still running
    print(signal.getsignal(signal.SIGINT) is signal.default_int_handler)
""")


def test_ctrl_c_reaching_the_forkserver_and_workers_is_the_drivers_to_answer(tmp_path):
    """A terminal's Ctrl-C goes to the whole process group: the forkserver and the resource tracker
    (even while they start Python) and the workers (even mid-sample) ignore it, and say nothing; the
    driver keeps its own handler."""
    (tmp_path / "probe.py").write_text(PROBE)
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    out = subprocess.run([sys.executable, "-c", DRIVER], capture_output=True, text=True, timeout=120, env=env,
                         cwd=tmp_path)
    assert out.stdout.splitlines() == ["[10, 20, 30]", "[True, True]", "True"], out
    assert out.stderr == ""


def test_a_ctrl_c_lost_while_the_process_exits_is_dropped():
    """Lost in an exit callback: nothing is left to interrupt, so it is dropped, and no alarm
    outlives the interpreter's handlers (SIGALRM's default action would end the process, status -14,
    while the interpreter tears the modules down)."""
    code = textwrap.dedent("""
        import atexit, time
        from pcfbench.interrupts import redeliver_swallowed_interrupts
        redeliver_swallowed_interrupts()
        def exit_callback():
            raise KeyboardInterrupt  # Ctrl-C while an exit callback runs
        atexit.register(exit_callback)
        class TornDown:
            def __del__(self):
                time.sleep(0.05)  # the alarm the exit callback's interrupt armed would go off in here
        kept = TornDown()
        print("done")
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert (out.returncode, out.stdout, out.stderr) == (0, "done\n", "")
