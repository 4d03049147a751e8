"""Long work off Blender's main thread. An upload (whose build takes minutes for a face) or a bake runs its gRPC
calls on a worker thread, which never touches bpy; the operator's modal timer polls the job on the main thread,
shows its progress (the window manager's progress bar and the status bar), applies what the worker delivered
to Blender's data, and Esc cancels it: the worker's next progress callback or frame raises Cancelled, which
cancels the call, and the server stops the build or the stream.

Headless (blender -b, scripts) the operators run the same work synchronously (execute), and a test drives a
job through its modal path as the timer would.
"""

import queue
import threading

# Jobs whose worker runs: the operators refuse to start another one meanwhile (one character's upload, bake and
# preview would otherwise race on its data).
RUNNING = set()


class Cancelled(Exception):
    """Raised inside the worker once the artist cancelled the job."""


class Job:
    """work(job) runs on a worker thread: it may call job.progress(fraction, text), job.deliver(item) (what
    the main thread must apply: poll() returns it) and job.check() (raises Cancelled once cancelled); its
    return value is job.result, its exception job.error."""

    def __init__(self, work, name):
        self._work = work
        self._items = queue.Queue()
        self._lock = threading.Lock()
        self._fraction, self._text = 0.0, ""
        self._cancelled = threading.Event()
        self._done = threading.Event()
        self.result = None
        self.error = None
        self._on_item = None
        self._thread = threading.Thread(target=self._run, name=f"springblend-{name}", daemon=True)

    def start(self):
        RUNNING.add(self)
        self._thread.start()
        return self

    def run_here(self, on_item):
        """Runs the work on the calling thread (headless, scripts), handing each delivered item to on_item at
        once."""
        self._on_item = on_item
        self._run()

    def _run(self):
        try:
            self.result = self._work(self)
        except BaseException as error:  # noqa: BLE001 - handed to the main thread, which reports it
            self.error = error
        finally:
            self._done.set()
            RUNNING.discard(self)

    # The worker's side.
    def progress(self, fraction, text):
        with self._lock:
            self._fraction, self._text = min(max(float(fraction), 0.0), 1.0), str(text)
        self.check()

    def deliver(self, item):
        self.check()
        if self._on_item is not None:
            self._on_item(item)
        else:
            self._items.put(item)

    def check(self):
        if self._cancelled.is_set():
            raise Cancelled()

    # The main thread's side.
    def cancel(self):
        self._cancelled.set()

    @property
    def cancelled(self):
        return self._cancelled.is_set()

    def poll(self):
        """(items delivered since the last poll, fraction, text, done). `done` is True once the worker ended and
        every item it delivered was returned."""
        done = self._done.is_set()
        items = []
        while True:
            try:
                items.append(self._items.get_nowait())
            except queue.Empty:
                break
        with self._lock:
            fraction, text = self._fraction, self._text
        return items, fraction, text, done


class ModalJob:
    """The modal side of an operator that runs a Job: for an Operator whose prepare(context) returns the Job (not
    started), whose apply(context, items) and finish(context, job) run on the main thread (finish reports and
    returns the operator's result set), and whose failed(context, error) reports an error. invoke() runs
    execute() headless, where no timer or event loop exists; run_job() is execute's synchronous path."""

    def run_job(self, context):
        job = self.prepare(context)
        job.run_here(lambda item: self.apply(context, [item]))
        if job.error is not None:
            raise job.error
        return self.finish(context, job)

    POLL_SECONDS = 0.1

    def invoke(self, context, event):
        import bpy
        if bpy.app.background or context.window is None:
            return self.execute(context)
        try:
            self._job = self.prepare(context).start()
        except Exception as error:  # noqa: BLE001 - the operator's own error reporting
            return self.failed(context, error)
        window_manager = context.window_manager
        self._timer = window_manager.event_timer_add(self.POLL_SECONDS, window=context.window)
        window_manager.progress_begin(0, 1000)
        window_manager.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type == "ESC":
            self._job.cancel()
            context.workspace.status_text_set("springblend: cancelling...")
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        items, fraction, text, done = self._job.poll()
        try:
            if items and not self._job.cancelled:  # a cancelled job's late items are dropped
                self.apply(context, items)
        except Exception as error:  # noqa: BLE001
            self._job.cancel()
            self._end(context)
            return self.failed(context, error)
        context.window_manager.progress_update(int(1000 * fraction))
        if text:
            context.workspace.status_text_set(f"springblend: {text} (Esc cancels)")
        if not done:
            return {"RUNNING_MODAL"}
        self._end(context)
        if self._job.error is not None:  # Cancelled included: failed() reports it as a warning
            return self.failed(context, self._job.error)
        try:
            return self.finish(context, self._job)
        except Exception as error:  # noqa: BLE001
            return self.failed(context, error)

    def _end(self, context):
        window_manager = context.window_manager
        window_manager.event_timer_remove(self._timer)
        window_manager.progress_end()
        context.workspace.status_text_set(None)
