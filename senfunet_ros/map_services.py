"""The node's map services: ~/save_mesh, ~/save_map, ~/load_map and ~/reset (std_srvs/Trigger).

What each does with the pipeline, and the reply it sends: a handler never raises, a failure is
its reply (and an error in the log) and leaves the map as it was. The node owns the transport;
`MapServices` gets the parts it acts on: the pipeline, and the mesh publisher, whose subscribers are
told when the map is replaced or reset.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from senfunet_core.errors import InputError
from senfunet_ros import params as P
from senfunet_ros.mesh_publisher import MeshPublisher, mesh_period_s
from senfunet_ros.pipeline import Pipeline, mesh_paths


# what the node's parameters fix and a map must share: its sensors and what their grids mean
_MAP_FIELDS = ("sensors", "sensor_uses_rgb", "voxel_size_m", "band_m")


def _reason(err: Exception) -> str:
    """What an error says; an allocation's bare MemoryError says nothing by itself."""
    if isinstance(err, MemoryError):
        return (f"out of memory ({err})" if str(err) else "out of memory") + \
            " (free memory, e.g. with a lower max_map_blocks, and call the service again; the map is kept)"
    return str(err) or type(err).__name__


def _refuse_file_in_the_way(folder: Path, path: Path) -> None:
    """NotADirectoryError when `folder` or a folder above it is a file, so `path` cannot be made there
    (else the reply were mkdir's "[Errno 17] File exists: <it>")."""
    blocker = next((part for part in (folder, *folder.parents) if part.exists() and not part.is_dir()), None)
    if blocker is not None:
        raise NotADirectoryError(f"{blocker} is a file, not a folder, so {path} cannot be made")


class NothingToSave(InputError):
    """The map is empty, and saving it would replace files an earlier map wrote."""


def _plain(value: Any) -> Any:
    return tuple(value) if isinstance(value, (list, tuple)) else value


def _loaded_map_notes(engine: Any, want: Any, weights: str | None) -> list[str]:
    """Where a loaded map runs otherwise than the node's parameters say: what it was saved with rules
    the networks (its features were made by them) and the TSDF Fusion baseline (a grid of its own)."""
    import torch

    from senfunet_core.networks import load_weights, make_networks

    notes = []
    config = engine.config
    feature_nets, weighting_net = make_networks(config.sensor_uses_rgb, want.seed, config.weighting_tsdf_input)
    try:
        if weights is not None:
            load_weights(weights, feature_nets, weighting_net)
        same = all(torch.equal(mine, theirs) for net, loaded in zip([*feature_nets, weighting_net],
                                                                     [*engine.feature_nets, engine.weighting_net])
                   for mine, theirs in zip(net.state_dict().values(), loaded.state_dict().values()))
    except InputError:
        same = False
    if not same:
        notes.append(f"it runs with the networks saved in it (its features were made by them), not those of "
                     f"parameter weights ({weights or 'none: untrained'})")
    if config.tsdf_fusion != want.tsdf_fusion:
        notes.append("it keeps a TSDF Fusion baseline, though parameter tsdf_fusion is false: ~/save_mesh writes "
                     "tsdf_fusion.ply too" if config.tsdf_fusion else
                     "it was saved without a TSDF Fusion baseline, though parameter tsdf_fusion is true: ~/save_mesh "
                     "writes no tsdf_fusion.ply for it (one in output_dir is an earlier map's)")
    if config.alpha_dtype != want.alpha_dtype:
        notes.append(f"the weighting net runs in {config.alpha_dtype}, not {want.alpha_dtype} (see the log)")
    return notes


@dataclass
class MapServices:
    pipeline: Pipeline
    settings: Callable[[], P.Settings]  # the node's parameters now (they change at run time)
    # its lock is held while ~/load_map replaces the engine: no mesh update meanwhile
    mesh_publisher: MeshPublisher
    logger: Any  # the node's logger

    def save_meshes(self, output_dir: str | Path | None = None, *, hurry: bool = False) -> list[Path]:
        """Fused (filtered), per-sensor and TSDF Fusion meshes as PLY files; returns their paths. The
        weighting net first judges what it has not reached; `hurry` (a process being stopped): not, and
        the fused mesh alone, as it stands."""
        return self._save_meshes(output_dir, hurry=hurry)[0]

    def _save_meshes(self, output_dir: str | Path | None = None, *, hurry: bool = False) -> tuple[list[Path], str]:
        """`save_meshes`, and a note when output_dir holds a mesh file of an earlier map that this map
        does not replace (a TSDF Fusion mesh, from a map that kept the baseline)."""
        s = self.settings()
        # absolute: the replies name the files for clients in other processes (other working directories)
        out = Path(output_dir or s.output_dir).expanduser().absolute()
        tsdf_fusion = self.pipeline.engine.config.tsdf_fusion and not hurry
        sensors = () if hurry else s.sensor_names
        _refuse_file_in_the_way(out, out)
        self._keep_earlier_files(list(mesh_paths(out, sensors=sensors, tsdf_fusion=tsdf_fusion).values()))
        saved = self.pipeline.save_meshes(out, sensors=sensors, tsdf_fusion=tsdf_fusion, judge=not hurry)
        baseline = mesh_paths(out, sensors=(), tsdf_fusion=True)["tsdf_fusion"]
        note = (f" ({baseline} is an earlier map's: this map keeps no TSDF Fusion baseline)"
                if not tsdf_fusion and baseline.exists() else "")
        return [saved_mesh.path for saved_mesh in saved.values()], note

    def save_map_file(self) -> Path:
        """The whole map into `map_path`; returns the path."""
        path = self.map_path()
        _refuse_file_in_the_way(path.parent, path)
        self._keep_earlier_files([path])
        return self.pipeline.save_map(path)

    def _keep_earlier_files(self, paths: list[Path]) -> None:
        """Raises NothingToSave when the map is empty (nothing fused since the start, the last ~/reset or
        a restart with on_time_jump reset) and some of these files exist: empty files would replace what
        an earlier map saved there (a ~/save_mesh after a ~/reset, or a node stopping with
        save_on_shutdown before its sensors came)."""
        engine = self.pipeline.engine
        if sum(engine.frames_integrated.values()) or engine.grid.n_blocks or len(engine.archive):
            return
        existing = [str(path) for path in paths if path.exists()]
        if existing:
            raise NothingToSave(f"the map is empty (nothing fused since the node started or the map was reset), so "
                                f"{', '.join(existing)} {'were' if len(existing) > 1 else 'was'} left as "
                                f"{'they were' if len(existing) > 1 else 'it was'}; fuse first, call ~/load_map to go "
                                "on from a saved map, or remove the files to save an empty map there")

    def map_path(self) -> Path:
        """Parameter map_file; a relative path is in output_dir (absolute, as the replies name it)."""
        s = self.settings()
        path = Path(s.map_file).expanduser()
        return (path if path.is_absolute() else Path(s.output_dir).expanduser() / path).absolute()

    def save_mesh(self, request: Any, response: Any) -> Any:
        return self._reply(response, self._save_mesh, "saving failed: {err}; check parameter output_dir")

    def save_map(self, request: Any, response: Any) -> Any:
        return self._reply(response, lambda: f"wrote {self.save_map_file()}",
                           "saving the map failed: {err}; check parameters output_dir and map_file")

    def load_map(self, request: Any, response: Any) -> Any:
        return self._reply(response, self._load_map, "loading the map failed: {err}")

    def reset(self, request: Any, response: Any) -> Any:
        return self._reply(response, self.reset_map, "reset failed: {err}", log="map reset by ~/reset")

    def reset_map(self) -> str:
        """Forget the map and queued frames; subscribers get a DELETEALL right away (if that publication
        fails, the reset still stands: the next mesh update sends the whole, empty map)."""
        self.pipeline.reset()
        try:
            self.mesh_publisher.publish()
        except Exception as err:
            self.logger.warning(f"mesh update after ~/reset failed: {err!r}; the next one clears the mesh")
        return "map reset"

    def _save_mesh(self) -> str:
        # the weighting net first judges what it has not reached: on a large map during a stream that is
        # many seconds, which the caller (and the services queued behind it) should not wait for unexplained
        self.logger.info(f"~/save_mesh: judging what the weighting net has not reached yet (in turns, mesh updates "
                         f"between them), then writing the meshes into "
                         f"{Path(self.settings().output_dir).expanduser().absolute()}")
        self._judge_between_updates()
        spill = getattr(self.pipeline.engine.grid, "spill", None)
        on_disk = len(spill) if spill is not None else 0
        note = (f" (the per-sensor meshes leave out the {on_disk} blocks the map bound evicted; mesh.ply has them)"
                if on_disk else "")
        paths, earlier = self._save_meshes()
        return "wrote " + ", ".join(str(p) for p in paths) + note + earlier

    def _judge_between_updates(self) -> None:
        """The weighting net's catch-up before the meshes are made, in turns of half a mesh period with
        a mesh update after each: the meshes hold the map from their own catch-up to the last triangle,
        and the live mesh would stand still that long (on a large map during a stream, the whole
        backlog); they now find only what changed since the last turn. Ends when nothing is left to judge, or when a
        turn left no less than the one before (frames change the map as fast as the net judges it)."""
        engine = self.pipeline.engine
        period_s = mesh_period_s(self.settings().mesh_rate_hz)
        left_before = None
        while engine is self.pipeline.engine:  # not replaced meanwhile (~/load_map)
            engine.refresh_alpha(0.5 * period_s)
            left = engine.counters["alpha_backlog_blocks"]
            if left == 0 or (left_before is not None and left >= left_before):
                return
            left_before = left
            self.mesh_publisher.updates.wait_next(timeout_s=2.0 * period_s)  # none (failing, or none due): go on

    def _load_map(self) -> str:
        path = self.map_path()
        want = P.engine_config(self.settings())

        def check_and_configure(engine: Any) -> None:  # before the loaded engine replaces the node's
            differ = [f"{name} {_plain(getattr(engine.config, name))} (the node's {_plain(getattr(want, name))})"
                      for name in _MAP_FIELDS if _plain(getattr(engine.config, name)) != _plain(getattr(want, name))]
            if differ:
                raise InputError(f"{path} was made with other settings: {', '.join(differ)}; start the node with "
                                 "the map's parameters to load it")
            P.configure_engine(engine, self.settings())

        with self.mesh_publisher.lock:
            # it runs as the node's parameters say (arithmetic, threads, map bound, allocation policy), not as
            # when the map was saved
            engine = self.pipeline.load_map(path, run_config=want, configure=check_and_configure)
            # a parameter change racing the load reaches the loaded engine too; subscribers get it whole
            P.configure_engine(engine, self.settings())
            self.mesh_publisher.resend_all()
        notes = _loaded_map_notes(engine, want, P.engine_weights(self.settings()))
        spilled = len(engine.grid.spill) if engine.grid.spill is not None else 0
        on_disk = f" in memory and {spilled} on disk (evicted before the save; back when seen again)" if spilled else ""
        frames = sum(engine.frames_integrated.values())
        return (f"loaded {path}: {frames} frames, {engine.grid.n_blocks} blocks{on_disk}"
                + "".join(f"; {note}" for note in notes))

    def _reply(self, response: Any, action: Callable[[], str], failure: str, log: str | None = None) -> Any:
        try:
            response.message = action()
            response.success = True
            self.logger.info(log or response.message)
        except Exception as err:
            response.success = False
            response.message = failure.format(err=_reason(err))
            self.logger.error(response.message)
        return response
