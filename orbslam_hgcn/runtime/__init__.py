"""The running system: :class:`~orbslam_hgcn.runtime.system.System` wires the stages with
queues, threads and child processes (or runs them in order), with the stage runners, the
generic worker, the map lock, ORB extraction in a child process and the results a run
leaves behind. The only package that knows every stage; the commands live in
:mod:`orbslam_hgcn.app`."""
