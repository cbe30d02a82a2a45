"""A single-threaded rclpy executor that runs synchronous callbacks without rclpy's Tasks.

rclpy's :class:`~rclpy.executors.SingleThreadedExecutor` wraps every ready callback in a
Task (a coroutine, a handler object, two triggers of its guard condition) and, because
of those triggers, wakes once more with nothing to do after every batch of callbacks. For
a node receiving many small messages, such as the fusion node with one bearing per station
and epoch, this bookkeeping (about 30 µs per callback) costs as much Python time as the
node's own work per bearing.

:class:`LeanExecutor` keeps rclpy's semantics for single-threaded, synchronous callbacks and
does less per wake-up: one rcl wait set over the nodes' subscriptions, timers, services
and waitables (built as rclpy builds it); then the ready timers, subscriptions and services
are run directly, in that order, one message or request per ready entity and wake-up, as
rclpy does. Everything else goes through rclpy's own machinery, unchanged: ready
waitables (middleware events, with coroutine ``execute`` methods) and any entity whose
callback is a coroutine function run as rclpy Tasks, and while a Task is pending, or when a
node has clients or guard conditions, :meth:`spin_once` is rclpy's (so callback groups
are honoured where they can matter: a plain callback on one thread never overlaps another
one). Exceptions raised by a
callback propagate out of :meth:`spin_once`, as from rclpy's executor; after Ctrl-C or
another shutdown of the context the wait returns and :meth:`spin_once` raises
:class:`~rclpy.executors.ExternalShutdownException`.
"""

from contextlib import ExitStack
import inspect

from rclpy.exceptions import InvalidHandle
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor, \
    timeout_sec_to_nsec
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.subscription import Subscription
from rclpy.waitable import NumberOfEntities

MESSAGE_ONLY = Subscription.CallbackType.MessageOnly


def _in_use(stack, entities, waitables=False):
    """The ``entities`` whose handles (the waitables themselves) could be entered on
    ``stack``: not destroyed."""
    out = []
    for entity in entities:
        try:
            stack.enter_context(entity if waitables else entity.handle)
        except InvalidHandle:
            continue
        out.append(entity)
    return out


class LeanExecutor(SingleThreadedExecutor):
    """rclpy's single-threaded executor with synchronous callbacks run directly (module
    docstring). Use it as any executor: ``rclpy.spin(node, LeanExecutor())``."""

    def spin_once(self, timeout_sec=None):
        """Wait up to ``timeout_sec`` seconds (forever if None or negative, not at all if 0)
        for work, then run every ready timer, subscription, service and waitable once."""
        if self._is_shutdown:
            return
        if not self._context.ok():
            raise ExternalShutdownException()
        nodes = self.get_nodes()
        if self._tasks or any(any(node.clients) or any(node.guards) for node in nodes):
            return super().spin_once(timeout_sec)
        guards = (self._guard, self._sigint_gc)
        with ExitStack() as stack:
            # In use during the wait (a handle is destroyed only once released); an entity
            # destroyed but still listed is left out, as rclpy leaves it out.
            timers = _in_use(stack, (t for node in nodes for t in node.timers))
            subs = _in_use(stack, (s for node in nodes for s in node.subscriptions))
            services = _in_use(stack, (s for node in nodes for s in node.services))
            _in_use(stack, guards)
            pairs = [(node, w) for node in nodes for w in _in_use(stack, node.waitables, True)]
            count = NumberOfEntities(len(subs), len(guards), len(timers), 0, len(services))
            for _, waitable in pairs:
                count += waitable.get_num_entities()
            stack.enter_context(self._context.handle)
            wait_set = _rclpy.WaitSet(count.num_subscriptions, count.num_guard_conditions,
                                      count.num_timers, count.num_clients,
                                      count.num_services, count.num_events,
                                      self._context.handle)
            for t in timers:
                wait_set.add_timer(t.handle)
            for s in subs:
                wait_set.add_subscription(s.handle)
            for s in services:
                wait_set.add_service(s.handle)
            for g in guards:
                wait_set.add_guard_condition(g.handle)
            for _, waitable in pairs:
                waitable.add_to_wait_set(wait_set)
            wait_set.wait(timeout_sec_to_nsec(timeout_sec))
            if self._is_shutdown:
                return
            if not self._context.ok():
                raise ExternalShutdownException()
            ready_timers = set(wait_set.get_ready_entities('timer'))
            ready_subs = set(wait_set.get_ready_entities('subscription'))
            ready_services = set(wait_set.get_ready_entities('service'))
            ready_waitables = [p for p in pairs if p[1].is_ready(wait_set)]
        ready = [(t, self._take_timer, self._call_timer) for t in timers
                 if t.handle.pointer in ready_timers]
        ready += [(s, self._take_subscription, self._call_subscription) for s in subs
                  if s.handle.pointer in ready_subs]
        ready += [(s, self._take_service, self._call_service) for s in services
                  if s.handle.pointer in ready_services]
        for entity, take, call in ready:
            if self._tasks:     # a coroutine is pending: the rest is left to rclpy's spin_once
                return          # (still ready), which keeps its callback group's exclusion
            if not self._still_running():
                return
            if inspect.iscoroutinefunction(entity.callback):
                self._run_task(entity, None, take)
            else:
                call(entity)
        for node, waitable in ready_waitables:
            if self._tasks or not self._still_running():
                return
            self._run_task(waitable, node, self._take_waitable)

    def _still_running(self):
        """False once the executor is shut down; ExternalShutdownException once the context
        is (a callback of this batch, another thread or Ctrl-C may have done it): no further
        callback of the batch runs, as rclpy checks before each callback."""
        if self._is_shutdown:
            return False
        if not self._context.ok():
            raise ExternalShutdownException()
        return True

    def _run_task(self, entity, node, take):
        """Run ``entity`` the way rclpy's executor does: a Task over ``take`` (rclpy's own
        ``_take_*`` method); a Task that awaits something stays pending, and the next
        :meth:`spin_once` calls are rclpy's until it is done."""
        task = self._make_handler(entity, node, take)
        task()
        with self._tasks_lock:
            self._tasks = [t for t in self._tasks if not t[0].done()]
        if task.done():
            task.result()   # raises the callback's exception, as rclpy's spin_once does

    # An entity destroyed by an earlier callback of the same batch raises InvalidHandle when
    # entered: it is skipped, as rclpy's _take_* methods skip it.

    @staticmethod
    def _call_timer(timer):
        try:
            with timer.handle:
                if not timer.handle.is_timer_ready():  # cancelled since the wait (rclpy's check)
                    return
                timer.handle.call_timer()
        except InvalidHandle:
            return
        timer.callback()

    @staticmethod
    def _call_subscription(sub):
        try:
            with sub.handle:
                taken = sub.handle.take_message(sub.msg_type, sub.raw)
        except InvalidHandle:
            return
        if taken is None:
            return
        if sub._callback_type is MESSAGE_ONLY:
            sub.callback(taken[0])
        else:
            sub.callback(*taken)

    @staticmethod
    def _call_service(srv):
        try:
            with srv.handle:
                request, header = srv.handle.service_take_request(srv.srv_type.Request)
        except InvalidHandle:
            return
        if header is not None:
            srv.send_response(srv.callback(request, srv.srv_type.Response()), header)
