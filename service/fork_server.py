"""Imported first by the fork server (processes.PRELOAD), in it alone: the fork server ignores SIGTERM. A graceful
stop signals the server's whole process group; the server then releases its jobs and stops its processes, and the
fork server must outlive that to report their exits (it ends by itself once the server process has exited)."""
import signal

signal.signal(signal.SIGTERM, signal.SIG_IGN)
